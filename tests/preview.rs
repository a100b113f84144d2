//! `flame::motion::preview`: the PNG container checked byte by byte (chunk CRCs recomputed here
//! with a bitwise CRC-32, the image inflated back), and the drawing checked pixel by pixel on
//! poses whose screen positions are derived by hand from the module doc's camera and scale rules.
//!
//! The motions: SMPL's rest pose stood up in its Z-up world (root rotation Rx(+90°), 6D rows
//! `[1,0,0, 0,0,−1]`), with the left hip flexed 30° forward (body-frame Rx(−30°), rows
//! `[1,0,0, 0,cos,sin]`). Walking: the translation moves 0.1 m a frame along native −Y, the
//! character's forward (ROS +X), so the side camera looks from −Y and the figure faces right.
//! In place: the same pose turned 90° left (root Rz(+90°)·Rx(+90°), rows `[0,0,1, 1,0,0]`) and
//! never moved, so the camera falls back to the hips' facing and the panel looks the same.
//!
//! The animated GIF is decoded with the `gif` crate's decoder and composited frame by frame
//! (disposal "keep") back into the `Animation`'s images.

#![cfg(feature = "preview")]

use flame::motion::preview::{
    animate, contact_sheet, encode_gif, encode_png, write_gif, write_png, Animation,
    AnimationOptions, Image, Ink, PreviewOptions,
};
use flame::motion::{rest_offsets, Convention, Format, Poses, ReadOptions};

const IDENTITY_6D: [f32; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
const FLEX: f64 = std::f64::consts::PI / 6.0;
// SMPL-24 joints used below (docs/official/smpl.md#joint-order).
const PELVIS: usize = 0;
const L_HIP: usize = 1;
const SPINE1: usize = 3;
const L_KNEE: usize = 4;
const R_KNEE: usize = 5;
const R_ANKLE: usize = 8;
const R_FOOT: usize = 11;

/// `frames` rows of smpl24_6d features: root 6D `root`, left hip flexed, translation
/// `(0, −step·t, 0)`.
fn features(frames: usize, root: [f32; 6], step: f32) -> Vec<f32> {
    let (s, c) = (FLEX.sin() as f32, FLEX.cos() as f32);
    let mut x = Vec::new();
    for t in 0..frames {
        x.extend_from_slice(&[0.0, -step * t as f32, 0.0]);
        x.extend_from_slice(&root);
        for j in 1..24 {
            if j == L_HIP {
                x.extend_from_slice(&[1.0, 0.0, 0.0, 0.0, c, s]);
            } else {
                x.extend_from_slice(&IDENTITY_6D);
            }
        }
    }
    x
}

fn walking(frames: usize) -> Poses {
    let x = features(frames, [1.0, 0.0, 0.0, 0.0, 0.0, -1.0], 0.1);
    Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap()
}

fn in_place(frames: usize) -> Poses {
    let x = features(frames, [0.0, 0.0, 1.0, 1.0, 0.0, 0.0], 0.0);
    Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap()
}

/// The pose in ROS coordinates relative to the pelvis for a character facing +X: rest offsets
/// chained along the parents, the left leg (knee, ankle, foot) turned about the hip by the flex
/// (+X forward, +Z up: down goes to (sin, 0, −cos)).
fn pose_facing_x() -> Vec<[f64; 3]> {
    let parents = Format::Smpl24Rot6d.skeleton().parents();
    let off = rest_offsets(Format::Smpl24Rot6d, Convention::Ros);
    let mut p = vec![[0.0f64; 3]; 24];
    for j in 1..24 {
        let q = p[parents[j] as usize];
        p[j] = [0, 1, 2].map(|k| q[k] + off[3 * j + k] as f64);
    }
    let (s, c) = (FLEX.sin(), FLEX.cos());
    let hip = p[L_HIP];
    for j in [L_KNEE, 7, 10] {
        let d = [0, 1, 2].map(|k| p[j][k] - hip[k]);
        p[j] = [
            hip[0] + c * d[0] - s * d[2],
            hip[1] + d[1],
            hip[2] + s * d[0] + c * d[2],
        ];
    }
    p
}

/// Where a joint of [`pose_facing_x`] lands in a default 160 × 240 panel whose left edge is
/// `x0`: ground row g = 240 − 24, band top 24, s = min(192 / (z_max + 0.2), 70 / (|Δu|_max + 0.1)).
struct Expected {
    p: Vec<[f64; 3]>,
    ground: f64,
    scale: f64,
}

impl Expected {
    fn new() -> Expected {
        let p = pose_facing_x();
        let ground = p.iter().map(|v| v[2]).fold(f64::MAX, f64::min);
        let top = p.iter().map(|v| v[2] - ground).fold(0.0, f64::max);
        let ahead = p.iter().map(|v| v[0].abs()).fold(0.0, f64::max);
        let scale = (192.0 / (top + 0.2)).min(70.0 / (ahead + 0.1));
        Expected { p, ground, scale }
    }

    /// Screen position of the point `f` of the way from joint `a` to joint `b`.
    fn at(&self, x0: u32, a: usize, b: usize, f: f64) -> (u32, u32) {
        let v = [0, 2].map(|k| self.p[a][k] + f * (self.p[b][k] - self.p[a][k]));
        let x = f64::from(x0) + 80.0 + v[0] * self.scale;
        let y = 216.0 - (v[1] - self.ground) * self.scale;
        (x.floor() as u32, y.floor() as u32)
    }
}

/// The hand-derived pixels of one figure panel.
fn check_figure(img: &Image, x0: u32, what: &str) {
    let e = Expected::new();
    let ink = |(x, y): (u32, u32)| img.ink(x, y).unwrap();
    assert_eq!(ink((x0 + 40, 216)), Ink::Ground, "{what}: ground line");
    assert_eq!(ink((x0 + 40, 215)), Ink::Background, "{what}: above ground");
    assert_eq!(
        ink(e.at(x0, PELVIS, SPINE1, 0.4)),
        Ink::Spine,
        "{what}: spine"
    );
    // The camera is on the character's right: the right shin is in front of the left leg.
    assert_eq!(
        ink(e.at(x0, R_KNEE, R_ANKLE, 0.5)),
        Ink::Right,
        "{what}: right shin"
    );
    assert_eq!(
        ink(e.at(x0, L_KNEE, L_KNEE, 0.0)),
        Ink::Left,
        "{what}: knee"
    );
    // Facing right, not mirrored: the toes and the flexed knee are right of the pelvis.
    let toe = e.at(x0, R_FOOT, R_FOOT, 0.0);
    assert_eq!(ink(toe), Ink::Right, "{what}: toe");
    assert!(toe.0 > e.at(x0, R_ANKLE, R_ANKLE, 0.0).0 + 5, "{what}: toe");
    assert!(e.at(x0, L_KNEE, L_KNEE, 0.0).0 > x0 + 95, "{what}: knee");
}

/// A decoded PNG: IHDR fields, palette, one palette index per pixel.
struct Png {
    width: u32,
    height: u32,
    palette: Vec<[u8; 3]>,
    index: Vec<u8>,
}

/// CRC-32 one bit at a time (reflected 0xEDB88320, init and final xor all ones).
fn bitwise_crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 == 1 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn be32(b: &[u8]) -> u32 {
    u32::from_be_bytes(b[..4].try_into().unwrap())
}

fn decode_png(bytes: &[u8]) -> Png {
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "signature");
    let mut at = 8;
    let mut kinds = Vec::new();
    let (mut ihdr, mut palette, mut idat) = (Vec::new(), Vec::new(), Vec::new());
    while at < bytes.len() {
        let len = be32(&bytes[at..]) as usize;
        let kind = &bytes[at + 4..at + 8];
        let data = &bytes[at + 8..at + 8 + len];
        let crc = be32(&bytes[at + 8 + len..]);
        assert_eq!(crc, bitwise_crc32(&bytes[at + 4..at + 8 + len]), "CRC");
        kinds.push(String::from_utf8(kind.to_vec()).unwrap());
        match kind {
            b"IHDR" => ihdr = data.to_vec(),
            b"PLTE" => palette = data.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            b"IDAT" => idat.extend_from_slice(data),
            _ => {}
        }
        at += 12 + len;
    }
    assert_eq!(at, bytes.len());
    assert_eq!(kinds, ["IHDR", "PLTE", "IDAT", "IEND"]);
    assert_eq!(ihdr.len(), 13);
    // 8-bit palette, deflate, standard filters, no interlace.
    assert_eq!(&ihdr[8..], &[8, 3, 0, 0, 0]);
    let (width, height) = (be32(&ihdr), be32(&ihdr[4..]));
    let raw = miniz_oxide::inflate::decompress_to_vec_zlib(&idat).unwrap();
    assert_eq!(raw.len(), (width as usize + 1) * height as usize);
    let mut index = Vec::new();
    for row in raw.chunks(width as usize + 1) {
        assert_eq!(row[0], 0, "filter type");
        index.extend_from_slice(&row[1..]);
    }
    assert!(index.iter().all(|&i| (i as usize) < palette.len()));
    Png {
        width,
        height,
        palette,
        index,
    }
}

#[test]
fn png_round_trips_the_image() {
    let img = contact_sheet(&walking(15), &PreviewOptions::default()).unwrap();
    let bytes = encode_png(&img);
    let png = decode_png(&bytes);
    assert_eq!((png.width, png.height), (8 * 160 + 240, 240));
    assert_eq!((img.width(), img.height()), (png.width, png.height));
    let want: Vec<[u8; 3]> = Ink::ALL.iter().map(|i| i.rgb()).collect();
    assert_eq!(png.palette, want);
    for y in 0..png.height {
        for x in 0..png.width {
            let i = png.index[(y * png.width + x) as usize];
            assert_eq!(Ink::ALL[i as usize], img.ink(x, y).unwrap(), "({x}, {y})");
        }
    }
    assert!(bytes.len() < 40_000, "{} bytes", bytes.len());
}

#[test]
fn walking_figures_stand_on_the_ground_facing_right() {
    let img = contact_sheet(&walking(15), &PreviewOptions::default()).unwrap();
    for panel in 0..8 {
        check_figure(&img, panel * 160, &format!("panel {panel}"));
    }
    let (w, h) = (img.width(), img.height());
    for (x, y) in [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1), (159, 239)] {
        assert_eq!(img.ink(x, y), Some(Ink::Background), "corner ({x}, {y})");
    }
    // Panel separators, and a label in the first panel's corner ("0").
    assert_eq!(img.ink(160, 100), Some(Ink::Border));
    assert!((4..10).any(|x| img.ink(x, 6) == Some(Ink::Label)));
}

#[test]
fn root_path_panel_shows_the_path_from_above() {
    // 15 frames, 0.1 m apart along the camera's u: 1.4 m × (1 m minimum) in a 240 × 240 panel
    // with 20 px margins → 200 / 1.4 px per metre, centred at (1280 + 120, 120).
    let img = contact_sheet(&walking(15), &PreviewOptions::default()).unwrap();
    let s = 200.0 / 1.4;
    let x = |m: f64| (1400.0 + (m - 0.7) * s).floor() as u32;
    let ink = |x: u32| img.ink(x, 120).unwrap();
    assert_eq!(ink(x(0.0)), Ink::Start);
    assert_eq!(ink(x(1.4)), Ink::End);
    assert_eq!(ink(x(0.7)), Ink::Path);
    // Sampled frames 0, 2, …, 14: the one at 0.6 m is marked.
    assert_eq!(ink(x(0.6)), Ink::Sample);
    // Nothing of the path off its line.
    for y in [60, 180] {
        let off = img.ink(1400, y).unwrap();
        assert!(matches!(off, Ink::Background | Ink::Border), "{off:?}");
    }
}

#[test]
fn in_place_motion_is_seen_from_the_side_it_faces() {
    let opts = PreviewOptions {
        frames: 2,
        ..PreviewOptions::default()
    };
    let img = contact_sheet(&in_place(5), &opts).unwrap();
    assert_eq!((img.width(), img.height()), (2 * 160 + 240, 240));
    check_figure(&img, 0, "in place");
    check_figure(&img, 160, "in place, last frame");
}

#[test]
fn same_motion_same_bytes() {
    let a = encode_png(&contact_sheet(&walking(15), &PreviewOptions::default()).unwrap());
    let b = encode_png(&contact_sheet(&walking(15), &PreviewOptions::default()).unwrap());
    assert_eq!(a, b);
    let path = std::env::temp_dir().join(format!("flame_preview_{}.png", std::process::id()));
    write_png(
        &path,
        &contact_sheet(&walking(15), &PreviewOptions::default()).unwrap(),
    )
    .unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), a);
    std::fs::remove_file(&path).unwrap();
    let missing = std::path::Path::new("/nonexistent/dir/x.png");
    let img = contact_sheet(&walking(2), &PreviewOptions::default()).unwrap();
    assert!(write_png(missing, &img)
        .unwrap_err()
        .to_string()
        .contains("/nonexistent/dir/x.png"));
}

#[test]
fn options_are_checked_and_frames_clamped() {
    let poses = walking(3);
    let err = |opts: PreviewOptions| contact_sheet(&poses, &opts).unwrap_err().to_string();
    let d = PreviewOptions::default();
    assert!(err(PreviewOptions { frames: 0, ..d }).contains("frames must be at least 1"));
    assert!(err(PreviewOptions {
        panel_width: 0,
        ..d
    })
    .contains("too small"));
    assert!(err(PreviewOptions {
        panel_height: 8,
        ..d
    })
    .contains("too small"));
    let e = err(PreviewOptions {
        panel_width: 10_000,
        ..d
    });
    assert!(e.contains("30240x240") && e.contains("limit"), "{e}");
    // More frames than the motion has: one panel per frame.
    let img = contact_sheet(&poses, &PreviewOptions { frames: 50, ..d }).unwrap();
    assert_eq!(img.width(), 3 * 160 + 240);
    // Wrapping rows, no path panel.
    let opts = PreviewOptions {
        columns: 2,
        root_path: false,
        ..d
    };
    let img = contact_sheet(&poses, &opts).unwrap();
    assert_eq!((img.width(), img.height()), (320, 480));
    let empty = Poses::decode(Format::Smpl24Rot6d, &[], 0, &ReadOptions::default()).unwrap();
    assert!(contact_sheet(&empty, &d).is_err());
}

#[test]
fn degenerate_humanml_motion_still_draws() {
    // All-zero features: every joint on the root. Nothing to see, but no panic or NaN trouble.
    let x = vec![0.0f32; 4 * Format::HumanMl263.feature_dim()];
    let poses = Poses::decode(Format::HumanMl263, &x, 4, &ReadOptions::default()).unwrap();
    let img = contact_sheet(&poses, &PreviewOptions::default()).unwrap();
    assert_eq!((img.width(), img.height()), (4 * 160 + 240, 240));
    decode_png(&encode_png(&img));
}

/// A walk cycle for looking at: 1 s stride cycle at 1.2 m/s heading 30° off native −Y, legs
/// swinging ±25° with the knees bending on the swing, arms lowered 70° from the T-pose and
/// swinging against the legs.
fn walk_cycle(frames: usize) -> Poses {
    use flame::motion::rotation::{axis_angle, mul, to_6d_rows};
    let deg = std::f64::consts::PI / 180.0;
    let (x_axis, z_axis) = ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
    let yaw = 30.0 * deg;
    let root = mul(&axis_angle(&z_axis, yaw), &axis_angle(&x_axis, 90.0 * deg));
    let mut x = Vec::new();
    for t in 0..frames {
        let phase = 2.0 * std::f64::consts::PI * t as f64 / 20.0;
        let d = 0.06 * t as f64;
        x.extend_from_slice(&[(d * yaw.sin()) as f32, (-d * yaw.cos()) as f32, 0.0]);
        let swing = 25.0 * deg * phase.sin();
        let mut local = vec![[0.0f64; 6]; 24];
        for (j, l) in local.iter_mut().enumerate() {
            let m = match j {
                0 => root,
                1 => axis_angle(&x_axis, -swing),
                2 => axis_angle(&x_axis, swing),
                4 => axis_angle(&x_axis, 40.0 * deg * phase.cos().max(0.0)),
                5 => axis_angle(&x_axis, 40.0 * deg * (-phase.cos()).max(0.0)),
                16 => mul(
                    &axis_angle(&x_axis, -0.8 * swing),
                    &axis_angle(&z_axis, -70.0 * deg),
                ),
                17 => mul(
                    &axis_angle(&x_axis, 0.8 * swing),
                    &axis_angle(&z_axis, 70.0 * deg),
                ),
                _ => axis_angle(&x_axis, 0.0),
            };
            *l = to_6d_rows(&m);
        }
        x.extend(local.iter().flatten().map(|&v| v as f32));
    }
    Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap()
}

/// Writes a walk's sheet to `$TMPDIR/preview_example.png` for a human to look at.
#[test]
#[ignore]
fn example_sheet() {
    let img = contact_sheet(&walk_cycle(60), &PreviewOptions::default()).unwrap();
    let path = std::env::temp_dir().join("preview_example.png");
    write_png(&path, &img).unwrap();
    println!("{} ({} bytes)", path.display(), encode_png(&img).len());
}

/// A decoded GIF: screen size, global palette, repeat, and per frame its delay, rectangle
/// and palette indices.
struct Gif {
    width: u32,
    height: u32,
    palette: Vec<[u8; 3]>,
    repeat: gif::Repeat,
    frames: Vec<GifFrame>,
}

struct GifFrame {
    delay: u16,
    dispose: gif::DisposalMethod,
    rect: [u32; 4],
    transparent: Option<u8>,
    index: Vec<u8>,
}

fn decode_gif(bytes: &[u8]) -> Gif {
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::Indexed);
    let mut d = opts.read_info(bytes).unwrap();
    let palette = d
        .global_palette()
        .expect("a global palette")
        .chunks(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let (width, height) = (u32::from(d.width()), u32::from(d.height()));
    let mut frames = Vec::new();
    while let Some(f) = d.read_next_frame().unwrap() {
        assert!(f.palette.is_none(), "no local palettes");
        frames.push(GifFrame {
            delay: f.delay,
            dispose: f.dispose,
            rect: [f.left, f.top, f.width, f.height].map(u32::from),
            transparent: f.transparent,
            index: f.buffer.to_vec(),
        });
    }
    Gif {
        width,
        height,
        palette,
        repeat: d.repeat(),
        frames,
    }
}

/// Pastes each decoded frame onto the canvas and checks the canvas against the animation's
/// image after every frame: the changed rectangles must rebuild each image exactly.
fn check_composites(gif: &Gif, anim: &Animation) {
    assert_eq!(gif.frames.len(), anim.frames().len());
    let (w, h) = (gif.width, gif.height);
    let mut canvas = vec![0u8; (w * h) as usize];
    for (k, (f, img)) in gif.frames.iter().zip(anim.frames()).enumerate() {
        let [left, top, fw, fh] = f.rect;
        assert!(
            left + fw <= w && top + fh <= h,
            "frame {k} inside the screen"
        );
        if k == 0 {
            assert_eq!(f.rect, [0, 0, w, h], "the first frame is whole");
        }
        assert_eq!(f.dispose, gif::DisposalMethod::Keep);
        assert_eq!(f.index.len(), (fw * fh) as usize);
        for y in 0..fh {
            for x in 0..fw {
                let i = f.index[(y * fw + x) as usize];
                if Some(i) != f.transparent {
                    canvas[((top + y) * w + left + x) as usize] = i;
                }
            }
        }
        for y in 0..h {
            for x in 0..w {
                let i = canvas[(y * w + x) as usize] as usize;
                assert_eq!(
                    gif.palette[i],
                    img.ink(x, y).unwrap().rgb(),
                    "frame {k} ({x}, {y})"
                );
            }
        }
    }
}

#[test]
fn gif_has_a_frame_per_motion_frame_and_rebuilds_every_image() {
    let anim = animate(&walk_cycle(120), 20.0, &AnimationOptions::default()).unwrap();
    assert_eq!(anim.frames().len(), 120);
    assert_eq!(anim.source_frames(), (0..120).collect::<Vec<_>>());
    assert_eq!((anim.width(), anim.height()), (160 + 240, 240));
    assert_eq!(anim.fps(), 20.0);
    let bytes = encode_gif(&anim).unwrap();
    let gif = decode_gif(&bytes);
    assert_eq!((gif.width, gif.height), (400, 240));
    assert_eq!(gif.repeat, gif::Repeat::Infinite);
    // The inks, padded to a power of two.
    let inks: Vec<[u8; 3]> = Ink::ALL.iter().map(|i| i.rgb()).collect();
    assert_eq!(gif.palette.len(), 16);
    assert_eq!(&gif.palette[..inks.len()], &inks[..]);
    assert!(gif.frames.iter().all(|f| f.delay == 5));
    check_composites(&gif, &anim);
    // Later frames are rectangles of what changed, and the path panel's far corner never does.
    assert!(gif.frames[1..]
        .iter()
        .all(|f| f.rect[2] * f.rect[3] < 400 * 240));
    assert!(bytes.len() < 1_000_000, "{} bytes", bytes.len());
    println!("120-frame walk: {} bytes", bytes.len());
}

#[test]
fn first_frame_decodes_to_the_first_image_in_rgb() {
    let anim = animate(&walk_cycle(20), 20.0, &AnimationOptions::default()).unwrap();
    let bytes = encode_gif(&anim).unwrap();
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::RGBA);
    let mut d = opts.read_info(&bytes[..]).unwrap();
    let f = d.read_next_frame().unwrap().unwrap();
    assert_eq!((f.width, f.height), (400, 240));
    let img = &anim.frames()[0];
    for y in 0..240u32 {
        for x in 0..400u32 {
            let at = ((y * 400 + x) * 4) as usize;
            let rgb = img.ink(x, y).unwrap().rgb();
            assert_eq!(
                &f.buffer[at..at + 4],
                &[rgb[0], rgb[1], rgb[2], 255],
                "({x}, {y})"
            );
        }
    }
}

#[test]
fn resampled_rates_keep_the_duration() {
    let poses = walking(120);
    for (fps, count) in [(10.0f32, 60usize), (30.0, 180), (50.0, 299), (7.0, 42)] {
        let opts = AnimationOptions {
            fps,
            ..AnimationOptions::default()
        };
        let anim = animate(&poses, 20.0, &opts).unwrap();
        assert_eq!(anim.frames().len(), count, "{fps} fps");
        let want: Vec<usize> = (0..count)
            .map(|k| (k as f64 * 20.0 / fps as f64).round() as usize)
            .collect();
        assert_eq!(anim.source_frames(), want, "{fps} fps");
        assert!(anim.source_frames().iter().all(|&t| t < 120));
        let gif = decode_gif(&encode_gif(&anim).unwrap());
        assert_eq!(gif.frames.len(), count, "{fps} fps");
        let total: u32 = gif.frames.iter().map(|f| u32::from(f.delay)).sum();
        let exact = count as f64 * 100.0 / fps as f64;
        assert!(
            (f64::from(total) - exact).abs() <= 1.0,
            "{fps} fps: {total} cs"
        );
        assert!(gif.frames.iter().all(|f| f.delay >= 2), "{fps} fps");
        if fps == 30.0 {
            // Repeated motion frames: unchanged GIF frames still composite right.
            check_composites(&gif, &anim);
        }
    }
}

#[test]
fn animation_frames_show_the_figure_its_ticks_and_where_it_is() {
    // Every frame holds the same pose, so the scale is the sheet's and the side panel is the
    // sheet's first panel plus ticks.
    let anim = animate(&walking(15), 20.0, &AnimationOptions::default()).unwrap();
    let e = Expected::new();
    for (k, img) in anim.frames().iter().enumerate() {
        check_figure(img, 0, &format!("frame {k}"));
        assert_eq!(img.ink(160, 100), Some(Ink::Border), "separator");
    }
    // Ticks hang under the ground line every 0.5 m and scroll 0.1 m a frame to the left.
    let ticks = |k: usize| -> Vec<u32> {
        let img = &anim.frames()[k];
        (0..160)
            .filter(|&x| img.ink(x, 222) == Some(Ink::Ground))
            .collect()
    };
    let centres = |k: usize| -> Vec<f64> {
        let mut out: Vec<Vec<u32>> = Vec::new();
        for x in ticks(k) {
            match out.last_mut() {
                Some(run) if *run.last().unwrap() + 1 == x => run.push(x),
                _ => out.push(vec![x]),
            }
        }
        out.iter()
            .map(|r| r.iter().map(|&x| f64::from(x)).sum::<f64>() / r.len() as f64)
            .collect()
    };
    let c0 = centres(0);
    assert!(c0.len() >= 2, "{c0:?}");
    for pair in c0.windows(2) {
        assert!((pair[1] - pair[0] - 0.5 * e.scale).abs() <= 1.0, "{c0:?}");
    }
    let c1 = centres(1);
    let shift = 0.1 * e.scale;
    assert!(
        c1.iter()
            .any(|&x| c0.iter().any(|&y| (y - shift - x).abs() <= 1.0)),
        "{c0:?} → {c1:?}"
    );
    assert_eq!(ticks(0), ticks(5), "0.5 m later the ticks line up again");
    assert_ne!(ticks(0), ticks(1));
    assert_eq!(anim.frames()[0].ink(40, 215), Some(Ink::Background));
    // The path panel: the sheet's geometry, centred at (160 + 120, 120); the current pelvis
    // marked on top of the start and end dots.
    let s = 200.0 / 1.4;
    let x = |m: f64| (280.0 + (m - 0.7) * s).floor() as u32;
    let at = |k: usize, m: f64| anim.frames()[k].ink(x(m), 120).unwrap();
    assert_eq!(at(0, 0.0), Ink::Sample);
    assert_eq!(at(0, 0.7), Ink::Path);
    assert_eq!(at(0, 1.4), Ink::End);
    assert_eq!(at(7, 0.0), Ink::Start);
    assert_eq!(at(7, 0.7), Ink::Sample);
    assert_eq!(at(14, 1.4), Ink::Sample);
    // Labels on, then off.
    assert!((4..10).any(|x| anim.frames()[0].ink(x, 6) == Some(Ink::Label)));
    let quiet = AnimationOptions {
        labels: false,
        ..AnimationOptions::default()
    };
    let plain = animate(&walking(15), 20.0, &quiet).unwrap();
    assert!(plain.frames()[0]
        .ink(0, 0)
        .into_iter()
        .chain(
            (0..20)
                .flat_map(|y| (0..40).map(move |x| (x, y)))
                .map(|(x, y)| { plain.frames()[0].ink(x, y).unwrap() })
        )
        .all(|i| i != Ink::Label));
}

#[test]
fn in_place_and_single_frame_motions_animate() {
    let anim = animate(&in_place(5), 20.0, &AnimationOptions::default()).unwrap();
    check_figure(&anim.frames()[4], 0, "in place");
    check_composites(&decode_gif(&encode_gif(&anim).unwrap()), &anim);
    let one = animate(&walking(1), 20.0, &AnimationOptions::default()).unwrap();
    let gif = decode_gif(&encode_gif(&one).unwrap());
    assert_eq!(gif.frames.len(), 1);
    assert_eq!(gif.frames[0].delay, 5);
    let small = AnimationOptions {
        panel_width: 32,
        panel_height: 32,
        ..AnimationOptions::default()
    };
    let tiny = animate(&walk_cycle(30), 20.0, &small).unwrap();
    assert_eq!((tiny.width(), tiny.height()), (64, 32));
    check_composites(&decode_gif(&encode_gif(&tiny).unwrap()), &tiny);
    let x = vec![0.0f32; 4 * Format::HumanMl263.feature_dim()];
    let zero = Poses::decode(Format::HumanMl263, &x, 4, &ReadOptions::default()).unwrap();
    let anim = animate(&zero, 20.0, &AnimationOptions::default()).unwrap();
    check_composites(&decode_gif(&encode_gif(&anim).unwrap()), &anim);
    // Far from the origin (1e20 m, where f64 steps are far over a tick) and travelling
    // absurdly fast: finite, so it draws, and the ticks terminate.
    for (start, step) in [(1e20f32, 0.1f32), (0.0, 1e30)] {
        let mut x = features(3, [1.0, 0.0, 0.0, 0.0, 0.0, -1.0], step);
        let row = x.len() / 3;
        for t in 0..3 {
            x[t * row] = start;
        }
        let far = Poses::decode(Format::Smpl24Rot6d, &x, 3, &ReadOptions::default()).unwrap();
        let anim = animate(&far, 20.0, &AnimationOptions::default()).unwrap();
        encode_gif(&anim).unwrap();
    }
}

#[test]
fn animation_options_are_checked() {
    let poses = walking(3);
    let d = AnimationOptions::default();
    let err =
        |fps: f32, opts: AnimationOptions| animate(&poses, fps, &opts).unwrap_err().to_string();
    for bad in [
        -1.0,
        50.5,
        1000.0,
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
    ] {
        let e = err(20.0, AnimationOptions { fps: bad, ..d });
        assert!(
            e.contains("fps must be above 0 and at most 50"),
            "{bad}: {e}"
        );
    }
    assert!(animate(&poses, 20.0, &AnimationOptions { fps: 50.0, ..d }).is_ok());
    // The motion's own rate must itself be usable.
    assert!(err(60.0, d).contains("the motion's rate 60"));
    for bad in [0.0, -20.0, f32::NAN, f32::INFINITY] {
        let e = err(bad, AnimationOptions { fps: 10.0, ..d });
        assert!(e.contains("motion's frame rate"), "{bad}: {e}");
    }
    assert!(err(20.0, AnimationOptions { fps: 1e-4, ..d }).contains("too low"));
    assert!(err(
        20.0,
        AnimationOptions {
            panel_width: 31,
            ..d
        }
    )
    .contains("too small"));
    assert!(err(
        20.0,
        AnimationOptions {
            panel_height: 0,
            ..d
        }
    )
    .contains("too small"));
    let e = err(
        20.0,
        AnimationOptions {
            panel_width: 20_000,
            ..d
        },
    );
    assert!(e.contains("20240x240") && e.contains("limit"), "{e}");
    let e = err(
        20.0,
        AnimationOptions {
            panel_width: 8000,
            panel_height: 8000,
            ..d
        },
    );
    assert!(e.contains("limit"), "{e}");
    // 3 frames at 0.01 fps shown at 50 fps: 15000 frames, over the total pixel bound.
    let e = err(0.01, AnimationOptions { fps: 50.0, ..d });
    assert!(e.contains("over all frames"), "{e}");
    let big = AnimationOptions {
        panel_width: 4000,
        panel_height: 4000,
        ..d
    };
    let e = animate(&walking(10), 20.0, &big).unwrap_err().to_string();
    assert!(e.contains("over all frames"), "{e}");
    let empty = Poses::decode(Format::Smpl24Rot6d, &[], 0, &ReadOptions::default()).unwrap();
    assert!(animate(&empty, 20.0, &d)
        .unwrap_err()
        .to_string()
        .contains("no frames"));
}

#[test]
fn gif_is_deterministic_and_written() {
    let anim = animate(&walking(10), 20.0, &AnimationOptions::default()).unwrap();
    let a = encode_gif(&anim).unwrap();
    let again = animate(&walking(10), 20.0, &AnimationOptions::default()).unwrap();
    assert_eq!(anim, again);
    assert_eq!(encode_gif(&again).unwrap(), a);
    assert_eq!(&a[..6], b"GIF89a");
    assert_eq!(a.last(), Some(&0x3b), "trailer");
    let path = std::env::temp_dir().join(format!("flame_preview_{}.gif", std::process::id()));
    write_gif(&path, &anim).unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), a);
    std::fs::remove_file(&path).unwrap();
    let missing = std::path::Path::new("/nonexistent/dir/x.gif");
    assert!(write_gif(missing, &anim)
        .unwrap_err()
        .to_string()
        .contains("/nonexistent/dir/x.gif"));
}

/// Writes a walk's animation to `$TMPDIR/preview_example.gif` for a human to look at.
#[test]
#[ignore]
fn example_gif() {
    let anim = animate(&walk_cycle(120), 20.0, &AnimationOptions::default()).unwrap();
    let path = std::env::temp_dir().join("preview_example.gif");
    write_gif(&path, &anim).unwrap();
    let bytes = encode_gif(&anim).unwrap().len();
    println!(
        "{} ({} frames, {bytes} bytes)",
        path.display(),
        anim.frames().len()
    );
}
