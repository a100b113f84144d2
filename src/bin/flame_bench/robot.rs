//! `flame-bench robot [--urdf target/robots/gr1t2.urdf] [--link NAME] [--calls 20000] [--runs 7]`:
//! the cost of the robot model's kinematics per IK iteration, in microseconds per call on one
//! thread: [`flame::robot::forward`] alone, and `forward` plus one
//! [`flame::robot::jacobian_point`] of a link (default: the deepest link, the longest chain).
//! Calls cycle through 64 random configurations inside the limits. Medians over the runs; one
//! `RESULT` line. GR1T2's URDF comes from `bash tools/fetch_robots.sh`.

use std::hint::black_box;
use std::time::Instant;

use flame::robot::{forward, jacobian_point, Pose, Robot, RobotData};

use super::arg;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The link with the most ancestors.
fn deepest(robot: &Robot) -> usize {
    let mut depth = vec![0usize; robot.links().len()];
    for (i, l) in robot.links().iter().enumerate() {
        if let Some(p) = l.parent {
            depth[i] = depth[p] + 1;
        }
    }
    (0..depth.len()).max_by_key(|&i| depth[i]).unwrap_or(0)
}

pub fn robot_bench(args: &[String]) {
    let path: String = arg(args, "--urdf", "target/robots/gr1t2.urdf".to_string());
    let calls: usize = arg(args, "--calls", 20_000);
    let runs: usize = arg(args, "--runs", 7);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!("cannot read {path}: {e} (bash tools/fetch_robots.sh fetches GR1T2)")
    });
    let robot = Robot::from_urdf(&text).unwrap_or_else(|e| panic!("{path}: {e}"));
    let link_name: String = arg(args, "--link", String::new());
    let link = if link_name.is_empty() {
        deepest(&robot)
    } else {
        robot
            .link_index(&link_name)
            .unwrap_or_else(|| panic!("{path} has no link `{link_name}`"))
    };

    // 64 configurations from a fixed LCG, inside the limits (±1 rad for unbounded joints).
    let mut state = 7u64;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let limits = robot.joint_limits();
    let n = robot.dof_count();
    let configurations: Vec<(Pose, Vec<f64>)> = (0..64)
        .map(|_| {
            let base = Pose::from_xyz_rpy([next(), next(), 0.9], [next(), next(), 6.0 * next()]);
            let q = (0..n)
                .map(|i| {
                    let (lo, hi) = (limits.lower[i].max(-1.0), limits.upper[i].min(1.0));
                    lo + (hi - lo) * next()
                })
                .collect();
            (base, q)
        })
        .collect();

    let mut data = RobotData::new(&robot);
    let mut jac = vec![0.0; 6 * robot.nv()];
    let mut time = |with_jacobian: bool| {
        let t = Instant::now();
        for c in 0..calls {
            let (base, q) = &configurations[c % 64];
            forward(&robot, base, q, &mut data).expect("forward");
            if with_jacobian {
                jacobian_point(&robot, &data, link, [0.0, 0.0, -0.05], &mut jac).expect("jacobian");
            }
            black_box((&data, &jac));
        }
        t.elapsed().as_secs_f64() * 1e6 / calls as f64
    };
    let (mut fk, mut both) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        fk.push(time(false));
        both.push(time(true));
    }
    let (fk, both) = (median(fk), median(both));
    println!(
        "{}: {} links, {} dofs; forward {fk:.3} us, forward + Jacobian of `{}` {both:.3} us \
         (median of {runs} runs of {calls} calls, one thread)",
        robot.name(),
        robot.links().len(),
        n,
        robot.links()[link].name
    );
    println!(
        "RESULT robot={} links={} dofs={n} forward_us={fk:.4} forward_jacobian_us={both:.4}",
        robot.name(),
        robot.links().len()
    );
}
