//! A denoising step allocates nothing on the heap once the session's first step has sized its
//! buffers (issue 8). Counted with a global allocator wrapper over every thread of the process,
//! so the session's own workers count too; each model family, with and without guidance, on 1
//! and 2 threads, and with an edit mask set.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use flame::models::{Condition, MdmDenoiser, Model};
use flame::session::{Session, SessionParams};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.alloc_zeroed(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.realloc(ptr, layout, new_size)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// Allocations made by steps 2..=steps (the first step sizes the buffers), the fewest of three
/// runs of the session from a reset: the thread pool's work queues grow and shrink with how
/// the workers happen to be scheduled (on a loaded machine a queue can grow at any step), while
/// an allocation of libflame's own would recur in every run.
fn allocations_after_first_step(mut s: Session, steps: usize) -> usize {
    let mut fewest = usize::MAX;
    for _ in 0..3 {
        s.reset();
        s.step().unwrap();
        let before = ALLOCATIONS.load(Ordering::SeqCst);
        for _ in 1..steps {
            s.step().unwrap();
        }
        fewest = fewest.min(ALLOCATIONS.load(Ordering::SeqCst) - before);
        if fewest == 0 {
            break;
        }
    }
    fewest
}

/// 16 frames run every kernel on one thread; 120 frames split attention and the linear layers
/// across the pool.
const FRAMES: [usize; 2] = [16, 120];

fn params(frames: usize, threads: usize, guidance: f32, steps: usize) -> SessionParams {
    SessionParams {
        frames: Some(frames),
        steps: Some(steps),
        guidance: Some(guidance),
        seed: 5,
        threads,
        ..Default::default()
    }
}

fn flame_steps_do_not_allocate() {
    let model = Arc::new(Model::load(fixture("flame_tiny.safetensors")).unwrap());
    for frames in FRAMES {
        for threads in [1, 2] {
            for guidance in [1.0, 2.5] {
                let p = params(frames, threads, guidance, 8);
                let mut s = Session::new(model.clone(), &p).unwrap();
                s.set_prompt("a person walks forward").unwrap();
                let n = allocations_after_first_step(s, 8);
                assert_eq!(
                    n, 0,
                    "{frames} frames, {threads} threads, guidance {guidance}: {n} allocations"
                );
            }
        }
    }
}

fn flame_edit_steps_do_not_allocate() {
    let model = Arc::new(Model::load(fixture("flame_tiny.safetensors")).unwrap());
    let mut s = Session::new(model.clone(), &params(16, 2, 2.5, 8)).unwrap();
    s.set_prompt("a person walks forward").unwrap();
    let dim = model.motion_dim();
    let reference: Vec<f32> = (0..16 * dim)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.1)
        .collect();
    s.set_reference(&reference).unwrap();
    let mut mask = vec![0u8; 16 * dim];
    mask[..4 * dim].fill(1);
    s.set_mask(&mask).unwrap();
    let n = allocations_after_first_step(s, 8);
    assert_eq!(n, 0, "edited FLAME: {n} allocations");
}

fn mdm_and_flow_steps_do_not_allocate() {
    for file in ["mdm_tiny.safetensors", "motionfm_tiny.safetensors"] {
        let model = Arc::new(Model::load(fixture(file)).unwrap());
        let dim = match model.denoiser().as_any().downcast_ref::<MdmDenoiser>() {
            Some(m) => m.cond_dim(),
            None => unreachable!("{file} is an MDM-family file"),
        };
        let text = vec![0.1f32; dim];
        for (frames, threads) in [(16, 1), (16, 2), (120, 2)] {
            let mut s = Session::new(model.clone(), &params(frames, threads, 2.5, 8)).unwrap();
            s.set_condition(Condition::text_vector(text.clone()))
                .unwrap();
            let n = allocations_after_first_step(s, 8);
            assert_eq!(
                n, 0,
                "{file}, {frames} frames, {threads} threads: {n} allocations"
            );
        }
    }
}

fn finemogen_and_omg_steps_do_not_allocate() {
    use flame::stages::{BodyPart, Stage};
    let fmg = Arc::new(Model::load(fixture("finemogen_tiny.safetensors")).unwrap());
    for threads in [1, 2] {
        let mut s = Session::new(fmg.clone(), &params(40, threads, 6.5, 8)).unwrap();
        s.set_prompt("a person walks forward").unwrap();
        let n = allocations_after_first_step(s, 8);
        assert_eq!(n, 0, "FineMoGen, {threads} threads: {n} allocations");
        let mut s = Session::new(fmg.clone(), &params(55, threads, 6.5, 8)).unwrap();
        s.set_prompt_stages(&[
            Stage::new("a person walks", 24),
            Stage::new("a person jumps", 31).with_part(BodyPart::LeftArm, "waves"),
        ])
        .unwrap();
        let n = allocations_after_first_step(s, 8);
        assert_eq!(n, 0, "FineMoGen stages, {threads} threads: {n} allocations");
    }
    let omg = Arc::new(Model::load(fixture("omg_tiny.safetensors")).unwrap());
    for (threads, prompt) in [(1, "a person walks"), (2, "a person walks"), (2, "")] {
        let mut s = Session::new(omg.clone(), &params(48, threads, 4.5, 8)).unwrap();
        s.set_prompt(prompt).unwrap();
        let n = allocations_after_first_step(s, 8);
        assert_eq!(n, 0, "OMG {prompt:?}, {threads} threads: {n} allocations");
    }
}

/// One test in this binary: the test harness's own thread allocates when a test starts or ends
/// (its report), which would land in another test's count.
#[test]
fn steps_do_not_allocate() {
    flame_steps_do_not_allocate();
    flame_edit_steps_do_not_allocate();
    mdm_and_flow_steps_do_not_allocate();
    finemogen_and_omg_steps_do_not_allocate();
}
