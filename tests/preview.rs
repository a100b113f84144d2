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

#![cfg(feature = "preview")]

use flame::motion::preview::{contact_sheet, encode_png, write_png, Image, Ink, PreviewOptions};
use flame::motion::{rest_offsets, Convention, Format, Poses, ReadOptions};

const IDENTITY_6D: [f32; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
const FLEX: f64 = std::f64::consts::PI / 6.0;
// SMPL-24 joints used below (REFERENCE 5).
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
