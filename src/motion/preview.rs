//! Previews of a motion: a contact sheet (stick figures side by side, written as a PNG) and an
//! animation (the figure moving next to its root path, written as a looping GIF). Nothing here
//! reads or writes motion data; the drawing, the PNG chunks and their CRCs are ours, only zlib
//! compression comes from `miniz_oxide` and GIF encoding (LZW, blocks) from `gif` (the
//! `preview` feature).
//!
//! # The picture
//!
//! ```text
//! +--------+--------+-- … --+--------+-----------+
//! | 0      | 19     |       | 140    |  root     |
//! |   o    |   o    |       |   o    |  path,    |
//! |  /|\   |  /|\   |       |  /|\   |  seen     |
//! |  / \   |  / \   |       |  / \   |  from     |
//! | ------ | ------ |       | ------ |  above    |
//! +--------+--------+-- … --+--------+-----------+
//! ```
//!
//! [`PreviewOptions::frames`] frames, evenly spaced from the first to the last (fewer if the
//! motion is shorter), are drawn in `panel_width × panel_height` panels, left to right and
//! wrapping after [`PreviewOptions::columns`]; a `panel_height` wide root-path panel spans the
//! grid's height on the right. Positions are taken in the `ros` convention (Z up, metres).
//!
//! **Camera.** An orthographic side view whose screen-right axis `u` is the principal axis of
//! the pelvis's horizontal path, pointed from the first frame towards the last, so a walk reads
//! left to right. When the path spans less than 0.4 m along that axis (an in-place motion) `u`
//! is the character's forward at the first frame (from its hips), so it faces right. The
//! camera sits on the side `u × up` and looks at the figure; screen up is world up. Nothing is
//! mirrored: a figure walking forward is seen from its right side, left limbs behind.
//!
//! **Scale and placement**, one for all panels of a sheet. With `W × H` the panel size, the
//! ground line's top row is `g = H − H/10` and the figure band starts at `t = H/10`. The ground
//! height is the lowest joint over the whole motion. Each figure's pelvis is centred
//! horizontally in its panel, and a point at height `z` above the ground and `Δu` ahead of that
//! frame's pelvis lands at `(W/2 + Δu·s, g − z·s)` (pixel `(x, y)` covers `[x, x+1) × [y, y+1)`),
//! with `s = min((g − t) / (z_max + 0.2), (W/2 − W/16) / (|Δu|_max + 0.1))` pixels per metre over
//! the drawn frames (0.2 m leaves room for the head).
//!
//! **Colours** ([`Ink`]): left limbs blue, right limbs orange, pelvis–spine–head dark grey,
//! bones drawn far to near. The path panel shows the pelvis from above (screen right `u`,
//! screen up away from the side camera) on a 1 m grid (coarser when the path is long): the
//! path grey, the drawn frames purple, the start green, the end red. The panel fits the path's
//! extent, at least 1 m each way, centred. Frame numbers label the panels.
//!
//! # The animation
//!
//! ```text
//! +--------+-----------+
//! | 37     |  root     |
//! |   o    |  path,    |
//! |  /|\   |  --*----  |   * = the pelvis now
//! |  / \   |           |
//! | -'-'-- |           |
//! +--------+-----------+
//! ```
//!
//! [`animate`] draws every shown frame as a `panel_width × panel_height` side view (the sheet's
//! camera, colours and placement rules, with one scale over *all* the motion's frames) and, to
//! its right, the `panel_height` wide path panel: the whole path in grey on its grid, start
//! green, end red, and the current pelvis position purple on top. The side view follows the
//! pelvis, so ground ticks every 0.5 m of the camera axis `u` (at world positions `u = k·0.5`;
//! the step doubles while ticks would be under 4 pixels apart) hang under the ground line and
//! scroll as the figure travels. With [`AnimationOptions::labels`] the motion's frame number is
//! in the side panel's corner.
//!
//! **Timing.** With [`AnimationOptions::fps`] 0 there is one GIF frame per motion frame at the
//! motion's own rate (`source_fps`); otherwise GIF frame `k` shows motion frame
//! `round(k · source_fps / fps)` for as long as that is a frame of the motion. GIF delays are
//! whole centiseconds, rounded on the running total, `delay_k = round((k+1)·100/fps) −
//! round(k·100/fps)`, so the GIF lasts `count / fps` to within half a centisecond. Rates
//! outside (0, 50] are refused: browsers stretch delays under 2 cs to 10 cs.
//!
//! **Encoding** ([`encode_gif`]). One global palette (the [`Ink`]s, padded to 16 colours),
//! looping forever (NETSCAPE2.0). The first frame is whole; each later one is only the
//! bounding box of the pixels that changed since the frame before (disposal "keep"), with
//! the unchanged pixels inside it set to the transparent index 11, so what stands still costs
//! next to nothing: 120 frames of a walk at the defaults are about 150 KB.

use std::path::Path;

use super::convention::Convention;
use super::poses::Poses;
use super::rotation::Vec3;
use crate::error::{invalid_arg, Error, Result};

/// How a contact sheet is laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreviewOptions {
    /// Figures to draw, evenly spaced from the first frame to the last; clamped to the motion's
    /// length.
    pub frames: usize,
    /// Width of one figure panel, pixels.
    pub panel_width: u32,
    /// Height of one figure panel (and width of the root-path panel), pixels.
    pub panel_height: u32,
    /// Figure panels per row; 0 = all in one row.
    pub columns: usize,
    /// Draw the top-down root-path panel on the right.
    pub root_path: bool,
    /// Write the frame number in each panel's corner.
    pub labels: bool,
}

impl Default for PreviewOptions {
    /// Eight 160 × 240 panels in one row, root path and labels on: a 1520 × 240 sheet.
    fn default() -> Self {
        PreviewOptions {
            frames: 8,
            panel_width: 160,
            panel_height: 240,
            columns: 0,
            root_path: true,
            labels: true,
        }
    }
}

/// Smallest panel side that still leaves room for a figure.
const MIN_PANEL: u32 = 32;
/// Largest sheet side, and largest pixel count, accepted.
const MAX_SIDE: u64 = 16384;
const MAX_PIXELS: u64 = 64 << 20;
/// Below this travel along the principal axis (metres) a motion counts as in place.
const IN_PLACE: f64 = 0.4;
/// Spacing of an animation's ground ticks along the camera axis, metres.
const TICK: f64 = 0.5;
/// Largest GIF frame rate accepted: browsers stretch delays under 2 cs to 10 cs.
const MAX_FPS: f64 = 50.0;
/// Largest pixel count of an animation, all frames together.
const MAX_ANIMATION_PIXELS: u64 = 64 << 20;

/// The colours of a sheet; the discriminant is the PNG palette index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Ink {
    /// White: everything not drawn.
    Background = 0,
    /// Panel separators and the path panel's grid.
    Border = 1,
    /// The ground line under each figure (and an animation's ground ticks, every 0.5 m).
    Ground = 2,
    /// Bones and joints whose joint name starts with `L_` / `left_`.
    Left = 3,
    /// … `R_` / `right_`.
    Right = 4,
    /// Pelvis, spine, neck and head.
    Spine = 5,
    /// The pelvis's whole path, seen from above, in the path panel.
    Path = 6,
    /// The drawn frames' pelvis positions on the path.
    Sample = 7,
    /// Green mark: the pelvis at the first frame.
    Start = 8,
    /// Red mark: the pelvis at the last frame.
    End = 9,
    /// Frame numbers in the panels' corners.
    Label = 10,
}

impl Ink {
    /// Every ink, in palette order.
    pub const ALL: [Ink; 11] = [
        Ink::Background,
        Ink::Border,
        Ink::Ground,
        Ink::Left,
        Ink::Right,
        Ink::Spine,
        Ink::Path,
        Ink::Sample,
        Ink::Start,
        Ink::End,
        Ink::Label,
    ];

    /// sRGB colour.
    pub fn rgb(self) -> [u8; 3] {
        match self {
            Ink::Background => [255, 255, 255],
            Ink::Border => [225, 225, 225],
            Ink::Ground => [130, 130, 130],
            Ink::Left => [31, 119, 180],
            Ink::Right => [240, 120, 20],
            Ink::Spine => [50, 50, 50],
            Ink::Path => [170, 170, 170],
            Ink::Sample => [130, 90, 190],
            Ink::Start => [40, 160, 40],
            Ink::End => [215, 40, 40],
            Ink::Label => [110, 110, 110],
        }
    }
}

/// A palette image: one [`Ink`] per pixel, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    width: u32,
    height: u32,
    pixels: Vec<Ink>,
}

impl Image {
    fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            pixels: vec![Ink::Background; width as usize * height as usize],
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The ink at pixel `(x, y)`; `None` outside the image.
    pub fn ink(&self, x: u32, y: u32) -> Option<Ink> {
        (x < self.width && y < self.height)
            .then(|| self.pixels[y as usize * self.width as usize + x as usize])
    }

    /// Paints every pixel of `clip` inside `bbox` (x0, y0, x1, y1 in pixel units) whose centre
    /// passes `inside`.
    fn paint(&mut self, clip: Rect, bbox: [f64; 4], ink: Ink, inside: impl Fn(f64, f64) -> bool) {
        let lo = |v: f64, min: u32| v.floor().max(f64::from(min)) as u32;
        let hi = |v: f64, max: u32| v.ceil().clamp(0.0, f64::from(max)) as u32;
        let (x0, x1) = (lo(bbox[0], clip.x0), hi(bbox[2], clip.x1));
        let (y0, y1) = (lo(bbox[1], clip.y0), hi(bbox[3], clip.y1));
        for y in y0..y1 {
            let row = y as usize * self.width as usize;
            for x in x0..x1 {
                if inside(x as f64 + 0.5, y as f64 + 0.5) {
                    self.pixels[row + x as usize] = ink;
                }
            }
        }
    }

    fn fill_rect(&mut self, clip: Rect, r: Rect, ink: Ink) {
        let bbox = [r.x0, r.y0, r.x1, r.y1].map(f64::from);
        self.paint(clip, bbox, ink, |_, _| true);
    }

    fn disc(&mut self, clip: Rect, c: [f64; 2], radius: f64, ink: Ink) {
        let bbox = [c[0] - radius, c[1] - radius, c[0] + radius, c[1] + radius];
        self.paint(clip, bbox, ink, |x, y| {
            (x - c[0]).powi(2) + (y - c[1]).powi(2) <= radius * radius
        });
    }

    fn ring(&mut self, clip: Rect, c: [f64; 2], radius: f64, half_width: f64, ink: Ink) {
        let out = radius + half_width;
        let bbox = [c[0] - out, c[1] - out, c[0] + out, c[1] + out];
        self.paint(clip, bbox, ink, |x, y| {
            ((x - c[0]).hypot(y - c[1]) - radius).abs() <= half_width
        });
    }

    /// A thick segment with round ends: every pixel within `radius` of `a`–`b`.
    fn capsule(&mut self, clip: Rect, a: [f64; 2], b: [f64; 2], radius: f64, ink: Ink) {
        let bbox = [
            a[0].min(b[0]) - radius,
            a[1].min(b[1]) - radius,
            a[0].max(b[0]) + radius,
            a[1].max(b[1]) + radius,
        ];
        let d = [b[0] - a[0], b[1] - a[1]];
        let len2 = d[0] * d[0] + d[1] * d[1];
        self.paint(clip, bbox, ink, |x, y| {
            let t = if len2 > 0.0 {
                (((x - a[0]) * d[0] + (y - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            (x - a[0] - t * d[0]).powi(2) + (y - a[1] - t * d[1]).powi(2) <= radius * radius
        });
    }

    /// Writes `n` in the 3 × 5 digit font, `scale` pixels per font pixel, top-left at `at`.
    fn number(&mut self, clip: Rect, at: [u32; 2], n: usize, scale: u32, ink: Ink) {
        for (i, ch) in n.to_string().bytes().enumerate() {
            let glyph = DIGITS[(ch - b'0') as usize];
            let left = at[0] + i as u32 * 4 * scale;
            for bit in 0..15 {
                if glyph >> (14 - bit) & 1 == 1 {
                    let (gx, gy) = (left + bit % 3 * scale, at[1] + bit / 3 * scale);
                    let cell = Rect::new(gx, gy, scale, scale);
                    self.fill_rect(clip, cell, ink);
                }
            }
        }
    }
}

/// 3 × 5 digits, rows top to bottom, 3 bits per row (most significant = left).
const DIGITS: [u16; 10] = [
    0b111_101_101_101_111,
    0b010_110_010_010_111,
    0b111_001_111_100_111,
    0b111_001_111_001_111,
    0b101_101_111_001_001,
    0b111_100_111_001_111,
    0b111_100_111_101_111,
    0b111_001_010_010_010,
    0b111_101_111_101_111,
    0b111_101_111_001_111,
];

/// A pixel rectangle, `x0..x1 × y0..y1`.
#[derive(Clone, Copy, Debug)]
struct Rect {
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
}

impl Rect {
    fn new(x: u32, y: u32, w: u32, h: u32) -> Rect {
        Rect {
            x0: x,
            y0: y,
            x1: x + w,
            y1: y + h,
        }
    }

    fn width(&self) -> f64 {
        f64::from(self.x1 - self.x0)
    }

    fn height(&self) -> f64 {
        f64::from(self.y1 - self.y0)
    }
}

/// Where the panels go: a `columns × rows` grid of figure panels, then the path panel.
struct Grid {
    columns: u32,
    rows: u32,
    panel_w: u32,
    panel_h: u32,
    path_w: u32,
}

impl Grid {
    /// Checks the options against the motion and lays out `count` figure panels.
    fn new(opts: &PreviewOptions, count: usize) -> Result<Grid> {
        let (pw, ph) = (opts.panel_width, opts.panel_height);
        if opts.frames == 0 {
            return Err(invalid_arg!("preview frames must be at least 1"));
        }
        if pw < MIN_PANEL || ph < MIN_PANEL {
            return Err(invalid_arg!(
                "preview panel {pw}x{ph} is too small (at least {MIN_PANEL}x{MIN_PANEL} pixels)"
            ));
        }
        let columns = match opts.columns {
            0 => count,
            c => c.min(count),
        } as u64;
        let rows = (count as u64).div_ceil(columns);
        let path_w = if opts.root_path { ph as u64 } else { 0 };
        let width = columns.saturating_mul(pw as u64).saturating_add(path_w);
        let height = rows.saturating_mul(ph as u64);
        if width > MAX_SIDE || height > MAX_SIDE || width * height > MAX_PIXELS {
            return Err(invalid_arg!(
                "preview sheet would be {width}x{height} pixels; the limit is {MAX_SIDE} a side and \
                 {MAX_PIXELS} pixels (draw fewer frames, more columns or smaller panels)"
            ));
        }
        Ok(Grid {
            columns: columns as u32,
            rows: rows as u32,
            panel_w: pw,
            panel_h: ph,
            path_w: path_w as u32,
        })
    }

    fn size(&self) -> (u32, u32) {
        (
            self.columns * self.panel_w + self.path_w,
            self.rows * self.panel_h,
        )
    }

    fn panel(&self, i: usize) -> Rect {
        let (c, r) = (i as u32 % self.columns, i as u32 / self.columns);
        Rect::new(
            c * self.panel_w,
            r * self.panel_h,
            self.panel_w,
            self.panel_h,
        )
    }

    fn path_panel(&self) -> Rect {
        Rect::new(
            self.columns * self.panel_w,
            0,
            self.path_w,
            self.rows * self.panel_h,
        )
    }
}

/// The motion seen through the sheet's camera: per joint, `(u, up, depth towards the camera)`.
struct View {
    /// `[frames × joints]` screen coordinates, metres, up measured from the ground.
    points: Vec<Vec3>,
    /// `[frames]` pelvis `(u, w)` from above, `w = up × u` (away from the side camera).
    root: Vec<[f64; 2]>,
}

impl View {
    fn new(poses: &Poses) -> Result<View> {
        let p = poses.positions(Convention::Ros);
        let root: Vec<Vec3> = poses.root_translation(Convention::Ros);
        if let Some(i) = p.iter().position(|v| v.iter().any(|x| !x.is_finite())) {
            return Err(invalid_arg!(
                "preview: joint positions are not finite at frame {}",
                i / poses.joint_count()
            ));
        }
        let u = side_axis(poses, &p, &root);
        let ground = p.iter().map(|v| v[2]).fold(f64::INFINITY, f64::min);
        let along = |v: &Vec3| v[0] * u[0] + v[1] * u[1];
        let towards = |v: &Vec3| v[0] * u[1] - v[1] * u[0];
        Ok(View {
            points: p
                .iter()
                .map(|v| [along(v), v[2] - ground, towards(v)])
                .collect(),
            root: root.iter().map(|v| [along(v), -towards(v)]).collect(),
        })
    }
}

/// The screen-right axis (unit, horizontal `[x, y]`) of the side camera; see the module doc.
fn side_axis(poses: &Poses, p: &[Vec3], root: &[Vec3]) -> [f64; 2] {
    let facing = facing(poses, p);
    let n = root.len() as f64;
    let mean = root
        .iter()
        .fold([0.0; 2], |m, r| [m[0] + r[0] / n, m[1] + r[1] / n]);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for r in root {
        let (dx, dy) = (r[0] - mean[0], r[1] - mean[1]);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let axis = [angle.cos(), angle.sin()];
    let along = |v: &Vec3| v[0] * axis[0] + v[1] * axis[1];
    let (lo, hi) = root
        .iter()
        .map(along)
        .fold((f64::MAX, f64::MIN), |(l, h), a| (l.min(a), h.max(a)));
    if hi - lo < IN_PLACE {
        return facing.unwrap_or([1.0, 0.0]);
    }
    let travel = along(&root[root.len() - 1]) - along(&root[0]);
    let sign = if travel.abs() >= 0.05 {
        travel
    } else {
        facing.map_or(1.0, |f| f[0] * axis[0] + f[1] * axis[1])
    };
    if sign < 0.0 {
        [-axis[0], -axis[1]]
    } else {
        axis
    }
}

/// The character's horizontal forward at the first frame, from the left hip to the right hip
/// (forward = left × up); `None` when the skeleton has no hips or they are stacked.
fn facing(poses: &Poses, p: &[Vec3]) -> Option<[f64; 2]> {
    let names = poses.format().skeleton().joint_names();
    let hip = |side: Ink| {
        names
            .iter()
            .position(|n| side_of(n) == side && n.to_ascii_lowercase().ends_with("hip"))
    };
    let (l, r) = (p[hip(Ink::Left)?], p[hip(Ink::Right)?]);
    let left = [l[0] - r[0], l[1] - r[1]];
    let len = left[0].hypot(left[1]);
    (len > 1e-6).then(|| [left[1] / len, -left[0] / len])
}

/// The ink of a joint's bone, from the joint's name.
fn side_of(name: &str) -> Ink {
    let n = name.to_ascii_lowercase();
    if n.starts_with("l_") || n.starts_with("left_") {
        Ink::Left
    } else if n.starts_with("r_") || n.starts_with("right_") {
        Ink::Right
    } else {
        Ink::Spine
    }
}

/// `count` frame indices evenly spaced over `0..total`, first and last included.
fn sample_frames(total: usize, count: usize) -> Vec<usize> {
    let count = count.min(total);
    if count <= 1 {
        return vec![0];
    }
    let gaps = count - 1;
    (0..count)
        .map(|i| (i * (total - 1) + gaps / 2) / gaps)
        .collect()
}

/// Draws `poses` as a contact sheet; see the module doc for what goes where. Errors on options
/// out of range (zero frames, panels under 32 pixels, sheets over 16384 pixels a side or 64 Mi
/// pixels) and on an empty motion.
pub fn contact_sheet(poses: &Poses, opts: &PreviewOptions) -> Result<Image> {
    if poses.frames() == 0 {
        return Err(invalid_arg!("preview: the motion has no frames"));
    }
    let grid = Grid::new(opts, opts.frames.min(poses.frames()))?;
    let frames = sample_frames(poses.frames(), opts.frames);
    let view = View::new(poses)?;
    let (w, h) = grid.size();
    let mut img = Image::new(w, h);
    let figures = Figures::new(poses, &view, &frames, grid.panel_w, grid.panel_h);
    for (i, &t) in frames.iter().enumerate() {
        let panel = grid.panel(i);
        figures.draw(&mut img, panel, t, false);
        if opts.labels {
            let scale = (grid.panel_h / 120).max(1);
            img.number(panel, [panel.x0 + 4, panel.y0 + 4], t, scale, Ink::Label);
        }
    }
    if opts.root_path {
        draw_root_path(&mut img, grid.path_panel(), &view.root, &frames);
    }
    draw_separators(&mut img, &grid, frames.len());
    Ok(img)
}

/// One-pixel lines between panels.
fn draw_separators(img: &mut Image, grid: &Grid, count: usize) {
    let all = Rect::new(0, 0, img.width, img.height);
    for i in 0..count {
        let p = grid.panel(i);
        if p.x0 > 0 {
            img.fill_rect(all, Rect::new(p.x0, p.y0, 1, grid.panel_h), Ink::Border);
        }
        if p.y0 > 0 {
            img.fill_rect(all, Rect::new(p.x0, p.y0, grid.panel_w, 1), Ink::Border);
        }
    }
    if grid.path_w > 0 {
        let p = grid.path_panel();
        img.fill_rect(all, Rect::new(p.x0, 0, 1, img.height), Ink::Border);
    }
}

/// The figure panels' shared scale and line widths.
struct Figures<'a> {
    view: &'a View,
    parents: &'a [i32],
    inks: Vec<Ink>,
    head: Option<usize>,
    joints: usize,
    /// Pixels per metre.
    scale: f64,
    /// Ground line's top row and bone radius, pixels.
    ground_row: u32,
    line: f64,
}

impl<'a> Figures<'a> {
    /// The scale fits the figures of `frames` in `panel_w × panel_h` panels.
    fn new(
        poses: &'a Poses,
        view: &'a View,
        frames: &[usize],
        panel_w: u32,
        panel_h: u32,
    ) -> Figures<'a> {
        let skel = poses.format().skeleton();
        let joints = skel.joint_count();
        let (w, h) = (f64::from(panel_w), f64::from(panel_h));
        let ground_row = panel_h - panel_h / 10;
        let top = f64::from(panel_h / 10);
        let (mut up, mut ahead) = (0.0f64, 0.0f64);
        for &t in frames {
            let pts = &view.points[t * joints..(t + 1) * joints];
            for q in pts {
                up = up.max(q[1]);
                ahead = ahead.max((q[0] - pts[0][0]).abs());
            }
        }
        let scale =
            ((f64::from(ground_row) - top) / (up + 0.2)).min((w / 2.0 - w / 16.0) / (ahead + 0.1));
        Figures {
            view,
            parents: skel.parents(),
            inks: skel.joint_names().iter().map(|n| side_of(n)).collect(),
            head: skel
                .joint_names()
                .iter()
                .position(|n| n.eq_ignore_ascii_case("head")),
            joints,
            scale,
            ground_row,
            line: (h / 110.0).max(1.0),
        }
    }

    /// Ground line (with [`Figures::ticks`] under it when `ticks`), then bones far to near,
    /// each with a disc on its joint and the head's ring.
    fn draw(&self, img: &mut Image, panel: Rect, t: usize, ticks: bool) {
        let pts = &self.view.points[t * self.joints..(t + 1) * self.joints];
        let gy = panel.y0 + self.ground_row;
        let inset = panel.x1.saturating_sub(panel.x0) / 20;
        let thick = (self.line * 0.8).round().max(1.0) as u32;
        let ground = Rect::new(
            panel.x0 + inset,
            gy,
            panel.width() as u32 - 2 * inset,
            thick,
        );
        img.fill_rect(panel, ground, Ink::Ground);
        let centre = f64::from(panel.x0) + panel.width() / 2.0;
        if ticks {
            self.ticks(img, panel, ground, centre, pts[0][0]);
        }
        let screen = |q: &Vec3| {
            [
                centre + (q[0] - pts[0][0]) * self.scale,
                f64::from(gy) - q[1] * self.scale,
            ]
        };
        let mut order: Vec<usize> = (1..self.joints).collect();
        let depth = |j: usize| pts[j][2] + pts[self.parents[j] as usize][2];
        order.sort_by(|&a, &b| depth(a).total_cmp(&depth(b)));
        let joint_r = self.line * 1.5;
        img.disc(panel, screen(&pts[0]), joint_r, self.inks[0]);
        for j in order {
            let (a, b) = (screen(&pts[self.parents[j] as usize]), screen(&pts[j]));
            img.capsule(panel, a, b, self.line, self.inks[j]);
            img.disc(panel, b, joint_r, self.inks[j]);
            if Some(j) == self.head {
                let spine = screen(&pts[self.grandparent(j)]);
                let r = 0.1 * self.scale;
                img.ring(panel, beyond(spine, b, r), r, self.line, self.inks[j]);
            }
        }
    }

    /// Tick marks hanging under the ground line `ground` at every [`TICK`] metres of the camera
    /// axis `u` (the step doubled until ticks are at least 4 pixels apart), placed relative to
    /// the pelvis at `pelvis_u`, which sits at column `centre`: they scroll as the figure moves.
    fn ticks(&self, img: &mut Image, panel: Rect, ground: Rect, centre: f64, pelvis_u: f64) {
        let mut step = TICK;
        while step * self.scale < 4.0 && step.is_finite() {
            step *= 2.0;
        }
        if !step.is_finite() {
            return;
        }
        let metres = |x: u32| pelvis_u + (f64::from(x) - centre) / self.scale;
        let (first, last) = (
            (metres(ground.x0) / step).ceil(),
            (metres(ground.x1) / step).floor(),
        );
        let width = f64::from(ground.y1 - ground.y0);
        let top = f64::from(ground.y1);
        let bottom = top + f64::from((panel.y1 - panel.y0) / 24).max(3.0);
        let clip = Rect {
            x0: ground.x0,
            x1: ground.x1,
            ..panel
        };
        // Counted, not stepped in floats: far from the origin `k + 1.0 == k`. Ticks are at
        // least 4 pixels apart, so there are never more than the ground line is wide.
        let count = (last - first + 1.0).clamp(0.0, f64::from(ground.x1 - ground.x0)) as u32;
        for i in 0..count {
            let x = centre + ((first + f64::from(i)) * step - pelvis_u) * self.scale;
            let left = (x - width / 2.0).round();
            img.paint(
                clip,
                [left, top, left + width, bottom],
                Ink::Ground,
                |_, _| true,
            );
        }
    }

    /// The head's skull goes on along the line from the upper spine (the head joint's
    /// grandparent), not along the neck bone, which SMPL tilts forward.
    fn grandparent(&self, j: usize) -> usize {
        let p = self.parents[j].max(0) as usize;
        self.parents[p].max(0) as usize
    }
}

/// The point `dist` pixels beyond `to` on the line from `from`.
fn beyond(from: [f64; 2], to: [f64; 2], dist: f64) -> [f64; 2] {
    let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
    let len = dx.hypot(dy).max(1e-9);
    [to[0] + dx / len * dist, to[1] + dy / len * dist]
}

/// The pelvis path from above, on a grid, with the drawn frames, start and end marked.
fn draw_root_path(img: &mut Image, panel: Rect, root: &[[f64; 2]], frames: &[usize]) {
    let map = PathMap::new(panel, root);
    map.draw_path(img, root);
    for &t in frames {
        map.mark(img, &root[t], 1.5, Ink::Sample);
    }
    map.mark(img, &root[0], 3.0, Ink::Start);
    map.mark(img, &root[root.len() - 1], 3.0, Ink::End);
}

/// The path panel's fit of the pelvis path: the path's extent (at least 1 m each way) centred
/// in the panel inside a margin.
struct PathMap {
    panel: Rect,
    /// Pixels per metre.
    scale: f64,
    /// The path's centre, metres, and where it lands, pixels.
    mid: [f64; 2],
    centre: [f64; 2],
    /// The path line's radius, pixels.
    line: f64,
}

impl PathMap {
    fn new(panel: Rect, root: &[[f64; 2]]) -> PathMap {
        let (lo, hi) = root
            .iter()
            .fold(([f64::MAX; 2], [f64::MIN; 2]), |(lo, hi), r| {
                (
                    [lo[0].min(r[0]), lo[1].min(r[1])],
                    [hi[0].max(r[0]), hi[1].max(r[1])],
                )
            });
        let margin = (panel.width().min(panel.height()) / 12.0).max(8.0);
        let extent = |k: usize| (hi[k] - lo[k]).max(1.0);
        let scale = ((panel.width() - 2.0 * margin) / extent(0))
            .min((panel.height() - 2.0 * margin) / extent(1));
        PathMap {
            panel,
            scale,
            mid: [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0],
            // On a pixel centre, so a level path is an odd number of rows thick, not jagged.
            centre: [
                f64::from(panel.x0 + panel.x1 / 2 - panel.x0 / 2) + 0.5,
                f64::from(panel.y0 + panel.y1 / 2 - panel.y0 / 2) + 0.5,
            ],
            line: (panel.height().min(panel.width()) / 160.0).max(1.0),
        }
    }

    fn screen(&self, r: &[f64; 2]) -> [f64; 2] {
        [
            self.centre[0] + (r[0] - self.mid[0]) * self.scale,
            self.centre[1] - (r[1] - self.mid[1]) * self.scale,
        ]
    }

    /// The grid, then the whole path in grey.
    fn draw_path(&self, img: &mut Image, root: &[[f64; 2]]) {
        draw_grid(img, self.panel, self.centre, self.scale);
        for pair in root.windows(2) {
            let (a, b) = (self.screen(&pair[0]), self.screen(&pair[1]));
            img.capsule(self.panel, a, b, self.line, Ink::Path);
        }
    }

    /// A dot of radius `line + grow` pixels at `r`.
    fn mark(&self, img: &mut Image, r: &[f64; 2], grow: f64, ink: Ink) {
        img.disc(self.panel, self.screen(r), self.line + grow, ink);
    }
}

/// Grid lines every metre (doubled until they are at least 12 pixels apart) through the path
/// panel, aligned so that one passes through the path's centre.
fn draw_grid(img: &mut Image, panel: Rect, centre: [f64; 2], scale: f64) {
    let mut step = 1.0;
    while step * scale < 12.0 {
        step *= 2.0;
    }
    let px = step * scale;
    for axis in 0..2 {
        let (lo, hi, c) = match axis {
            0 => (f64::from(panel.x0), f64::from(panel.x1), centre[0]),
            _ => (f64::from(panel.y0), f64::from(panel.y1), centre[1]),
        };
        let first = c - ((c - lo) / px).floor() * px;
        let mut v = first;
        while v < hi {
            let line = match axis {
                0 => Rect::new(v as u32, panel.y0, 1, panel.height() as u32),
                _ => Rect::new(panel.x0, v as u32, panel.width() as u32, 1),
            };
            img.fill_rect(panel, line, Ink::Border);
            v += px;
        }
    }
}

/// The image as an 8-bit palette PNG (one IDAT, no filtering, zlib level 9).
pub fn encode_png(img: &Image) -> Vec<u8> {
    let mut ihdr = Vec::with_capacity(13);
    ihdr.extend_from_slice(&img.width.to_be_bytes());
    ihdr.extend_from_slice(&img.height.to_be_bytes());
    // Bit depth 8, colour type 3 (palette), deflate, adaptive filtering, no interlace.
    ihdr.extend_from_slice(&[8, 3, 0, 0, 0]);
    let palette: Vec<u8> = Ink::ALL.iter().flat_map(|i| i.rgb()).collect();
    let w = img.width as usize;
    let mut raw = Vec::with_capacity((w + 1) * img.height as usize);
    for row in img.pixels.chunks_exact(w.max(1)) {
        raw.push(0);
        raw.extend(row.iter().map(|&i| i as u8));
    }
    let idat = miniz_oxide::deflate::compress_to_vec_zlib(&raw, 9);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    for (kind, data) in [
        (b"IHDR", &ihdr[..]),
        (b"PLTE", &palette[..]),
        (b"IDAT", &idat[..]),
        (b"IEND", &[][..]),
    ] {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = out.len();
        out.extend_from_slice(kind);
        out.extend_from_slice(data);
        let crc = crc32(&out[start..]);
        out.extend_from_slice(&crc.to_be_bytes());
    }
    out
}

/// [`encode_png`] written to `path`.
pub fn write_png(path: &Path, img: &Image) -> Result<()> {
    std::fs::write(path, encode_png(img)).map_err(|source| Error::Write {
        path: path.display().to_string(),
        source,
    })
}

/// How an animated preview is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnimationOptions {
    /// Width of the side-view panel, pixels.
    pub panel_width: u32,
    /// Height of the frame (and width of the root-path panel), pixels.
    pub panel_height: u32,
    /// Frames per second of the GIF, in (0, 50]; 0 = the motion's own rate (one GIF frame per
    /// motion frame). Other rates resample the motion (nearest frame).
    pub fps: f32,
    /// Write the motion's frame number in the side panel's corner.
    pub labels: bool,
}

impl Default for AnimationOptions {
    /// A 160 × 240 side panel and the 240 × 240 path panel (400 × 240 frames) at the motion's
    /// own rate, labelled.
    fn default() -> Self {
        AnimationOptions {
            panel_width: 160,
            panel_height: 240,
            fps: 0.0,
            labels: true,
        }
    }
}

/// The frames of an animated preview, ready for [`encode_gif`]: every frame is a full image of
/// the same size; frame `k` shows motion frame `source_frames()[k]` for `delays()[k]`
/// centiseconds.
#[derive(Clone, Debug, PartialEq)]
pub struct Animation {
    frames: Vec<Image>,
    delays: Vec<u16>,
    source: Vec<usize>,
    fps: f64,
}

impl Animation {
    /// The frames, in order (at least one).
    pub fn frames(&self) -> &[Image] {
        &self.frames
    }

    /// Each frame's display time, centiseconds.
    pub fn delays(&self) -> &[u16] {
        &self.delays
    }

    /// The motion frame each frame shows.
    pub fn source_frames(&self) -> &[usize] {
        &self.source
    }

    /// The GIF's frame rate: [`AnimationOptions::fps`], or the motion's when that is 0.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// Width in pixels of every frame (side view plus path panel).
    pub fn width(&self) -> u32 {
        self.frames[0].width
    }

    /// Height in pixels of every frame ([`AnimationOptions::panel_height`]).
    pub fn height(&self) -> u32 {
        self.frames[0].height
    }
}

/// Draws `poses` (recorded at `source_fps` frames per second) as an animation: each frame is
/// the side view of one motion frame next to the top-down root path with the pelvis's current
/// position marked; see the module doc. Errors on an empty motion, panels under 32 pixels,
/// frames over 16384 pixels a side or 64 Mi pixels, more than 64 Mi pixels over all frames, a
/// frame rate outside (0, 50] (or a `source_fps` that is not a positive finite number) and on
/// non-finite joint positions.
pub fn animate(poses: &Poses, source_fps: f32, opts: &AnimationOptions) -> Result<Animation> {
    let n = poses.frames();
    if n == 0 {
        return Err(invalid_arg!("preview: the motion has no frames"));
    }
    let (pw, ph) = (opts.panel_width, opts.panel_height);
    if pw < MIN_PANEL || ph < MIN_PANEL {
        return Err(invalid_arg!(
            "preview panel {pw}x{ph} is too small (at least {MIN_PANEL}x{MIN_PANEL} pixels)"
        ));
    }
    let (width, height) = (u64::from(pw) + u64::from(ph), u64::from(ph));
    if width > MAX_SIDE || height > MAX_SIDE || width * height > MAX_PIXELS {
        return Err(invalid_arg!(
            "preview animation frames would be {width}x{height} pixels; the limit is {MAX_SIDE} \
             a side and {MAX_PIXELS} pixels (use smaller panels)"
        ));
    }
    let source_fps = f64::from(source_fps);
    if !(source_fps.is_finite() && source_fps > 0.0) {
        return Err(invalid_arg!(
            "preview: the motion's frame rate must be a positive number, got {source_fps}"
        ));
    }
    let fps = f64::from(opts.fps);
    let rate = if fps == 0.0 { source_fps } else { fps };
    if !(rate.is_finite() && rate > 0.0 && rate <= MAX_FPS) {
        let what = if fps == 0.0 {
            format!("the motion's rate {rate} fps (set a GIF rate above 0 and at most {MAX_FPS})")
        } else {
            format!("{fps}")
        };
        return Err(invalid_arg!(
            "preview animation fps must be above 0 and at most {MAX_FPS} (browsers slow down faster GIFs), \
             got {what}"
        ));
    }
    if 100.0 / rate > f64::from(u16::MAX) {
        return Err(invalid_arg!(
            "preview animation fps {rate} is too low: a GIF frame lasts at most 655.35 s"
        ));
    }
    // An upper bound on the frame count, checked before anything is allocated.
    let bound = if fps == 0.0 {
        n as f64
    } else {
        (n as f64 * rate / source_fps).ceil() + 1.0
    };
    let frame_pixels = width * height;
    if bound * frame_pixels as f64 > MAX_ANIMATION_PIXELS as f64 {
        return Err(invalid_arg!(
            "preview animation would be {bound} frames of {width}x{height} pixels; the limit is \
             {MAX_ANIMATION_PIXELS} pixels over all frames (lower the fps or the panel size)"
        ));
    }
    let source = if fps == 0.0 {
        (0..n).collect()
    } else {
        resample(n, source_fps, rate)
    };
    let delays = delays(source.len(), rate);
    let view = View::new(poses)?;
    let all: Vec<usize> = (0..n).collect();
    let figures = Figures::new(poses, &view, &all, pw, ph);
    let side = Rect::new(0, 0, pw, ph);
    let path = Rect::new(pw, 0, ph, ph);
    // What does not move: the path panel with its start and end, and the separator.
    let mut base = Image::new(width as u32, height as u32);
    let map = PathMap::new(path, &view.root);
    map.draw_path(&mut base, &view.root);
    map.mark(&mut base, &view.root[0], 3.0, Ink::Start);
    map.mark(&mut base, &view.root[n - 1], 3.0, Ink::End);
    let all_pixels = Rect::new(0, 0, base.width, base.height);
    base.fill_rect(all_pixels, Rect::new(pw, 0, 1, ph), Ink::Border);
    let mut frames = Vec::with_capacity(source.len());
    for &t in &source {
        let mut img = base.clone();
        figures.draw(&mut img, side, t, true);
        if opts.labels {
            img.number(side, [4, 4], t, (ph / 120).max(1), Ink::Label);
        }
        map.mark(&mut img, &view.root[t], 1.5, Ink::Sample);
        frames.push(img);
    }
    Ok(Animation {
        frames,
        delays,
        source,
        fps: rate,
    })
}

/// The motion frame shown by each GIF frame `k` at `fps`: `round(k · source_fps / fps)`, for
/// as long as that is a frame of the motion's `frames`.
fn resample(frames: usize, source_fps: f64, fps: f64) -> Vec<usize> {
    let step = source_fps / fps;
    (0usize..)
        .map(|k| (k as f64 * step).round() as usize)
        .take_while(|&t| t < frames)
        .collect()
}

/// GIF delays of `count` frames at `fps`, centiseconds, rounded so the running total stays
/// within half a centisecond of the true time: `round((k + 1)·100/fps) − round(k·100/fps)`.
fn delays(count: usize, fps: f64) -> Vec<u16> {
    let at = |k: usize| (k as f64 * 100.0 / fps).round();
    (0..count).map(|k| (at(k + 1) - at(k)) as u16).collect()
}

/// The smallest rectangle holding every pixel where `a` and `b` differ; `None` if they are
/// the same. Both images have the same size.
fn changed(a: &Image, b: &Image) -> Option<Rect> {
    let w = a.width as usize;
    let mut found: Option<Rect> = None;
    for (y, (ra, rb)) in a
        .pixels
        .chunks_exact(w)
        .zip(b.pixels.chunks_exact(w))
        .enumerate()
    {
        let Some(first) = ra.iter().zip(rb).position(|(p, q)| p != q) else {
            continue;
        };
        let last = w
            - 1
            - ra.iter()
                .zip(rb)
                .rev()
                .position(|(p, q)| p != q)
                .unwrap_or(0);
        let (x0, x1, y) = (first as u32, last as u32 + 1, y as u32);
        found = Some(match found {
            None => Rect {
                x0,
                y0: y,
                x1,
                y1: y + 1,
            },
            Some(r) => Rect {
                x0: r.x0.min(x0),
                y0: r.y0,
                x1: r.x1.max(x1),
                y1: y + 1,
            },
        });
    }
    found
}

/// The palette slot after the inks (GIF pads the palette to 16 colours): in every frame but the
/// first, a pixel that did not change is this transparent index, so the frame below shows.
const UNCHANGED: u8 = Ink::ALL.len() as u8;

fn gif_error(e: gif::EncodingError) -> Error {
    invalid_arg!("preview: GIF encoding failed: {e}")
}

/// The animation as a looping GIF: one global palette (the [`Ink`]s), the first frame whole,
/// then each frame as the bounding box of the pixels that changed since the previous one
/// (disposal "keep"), so what stands still costs nothing.
pub fn encode_gif(anim: &Animation) -> Result<Vec<u8>> {
    let palette: Vec<u8> = Ink::ALL.iter().flat_map(|i| i.rgb()).collect();
    // `animate` keeps frames within 16384 pixels a side.
    let (w, h) = (anim.width() as u16, anim.height() as u16);
    let mut enc = gif::Encoder::new(Vec::new(), w, h, &palette).map_err(gif_error)?;
    enc.set_repeat(gif::Repeat::Infinite).map_err(gif_error)?;
    let mut prev: Option<&Image> = None;
    for (img, &delay) in anim.frames.iter().zip(&anim.delays) {
        let whole = Rect::new(0, 0, img.width, img.height);
        // An unchanged frame still needs an image: one pixel, redrawn as it was.
        let r = match prev {
            None => whole,
            Some(p) => changed(p, img).unwrap_or(Rect::new(0, 0, 1, 1)),
        };
        let mut buffer = Vec::with_capacity((r.x1 - r.x0) as usize * (r.y1 - r.y0) as usize);
        for y in r.y0..r.y1 {
            let row = y as usize * img.width as usize;
            let cols = row + r.x0 as usize..row + r.x1 as usize;
            let span = &img.pixels[cols.clone()];
            match prev {
                None => buffer.extend(span.iter().map(|&i| i as u8)),
                Some(p) => buffer.extend(span.iter().zip(&p.pixels[cols]).map(|(&i, &q)| {
                    if i == q {
                        UNCHANGED
                    } else {
                        i as u8
                    }
                })),
            }
        }
        let frame = gif::Frame {
            delay,
            dispose: gif::DisposalMethod::Keep,
            left: r.x0 as u16,
            top: r.y0 as u16,
            width: (r.x1 - r.x0) as u16,
            height: (r.y1 - r.y0) as u16,
            transparent: prev.map(|_| UNCHANGED),
            buffer: std::borrow::Cow::Owned(buffer),
            ..gif::Frame::default()
        };
        enc.write_frame(&frame).map_err(gif_error)?;
        prev = Some(img);
    }
    enc.into_inner().map_err(|e| gif_error(e.into()))
}

/// [`encode_gif`] written to `path`.
pub fn write_gif(path: &Path, anim: &Animation) -> Result<()> {
    std::fs::write(path, encode_gif(anim)?).map_err(|source| Error::Write {
        path: path.display().to_string(),
        source,
    })
}

/// CRC-32 (ISO-HDLC, reflected polynomial 0xEDB88320) as PNG chunks use it.
fn crc32(bytes: &[u8]) -> u32 {
    !bytes.iter().fold(!0u32, |c, &b| {
        CRC_TABLE[((c ^ b as u32) & 0xff) as usize] ^ (c >> 8)
    })
}

const CRC_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut n = 0;
    while n < 256 {
        let mut c = n as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 == 1 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        table[n] = c;
        n += 1;
    }
    table
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_matches_the_standard_check_value() {
        // The CRC catalogue's check value for "123456789".
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn samples_include_first_and_last() {
        assert_eq!(sample_frames(100, 8), [0, 14, 28, 42, 57, 71, 85, 99]);
        assert_eq!(sample_frames(3, 8), [0, 1, 2]);
        assert_eq!(sample_frames(5, 1), [0]);
        assert_eq!(sample_frames(1, 8), [0]);
    }

    #[test]
    fn sides_come_from_joint_names() {
        assert_eq!(side_of("L_Knee"), Ink::Left);
        assert_eq!(side_of("right_wrist"), Ink::Right);
        assert_eq!(side_of("Spine3"), Ink::Spine);
        assert_eq!(side_of("head"), Ink::Spine);
    }

    #[test]
    fn resampling_picks_the_nearest_frame() {
        assert_eq!(resample(6, 20.0, 10.0), [0, 2, 4]);
        assert_eq!(resample(4, 20.0, 30.0), [0, 1, 1, 2, 3, 3]);
        assert_eq!(resample(3, 20.0, 20.0), [0, 1, 2]);
        assert_eq!(resample(1, 20.0, 1.0), [0]);
    }

    #[test]
    fn delays_add_up_to_the_duration() {
        assert_eq!(delays(4, 20.0), [5, 5, 5, 5]);
        assert_eq!(delays(6, 30.0), [3, 4, 3, 3, 4, 3]);
        assert_eq!(delays(4, 40.0), [3, 2, 3, 2]);
        for fps in [7.0, 12.5, 24.0, 29.97, 50.0] {
            let total: u32 = delays(1000, fps).iter().map(|&d| u32::from(d)).sum();
            assert!((f64::from(total) - 100_000.0 / fps).abs() <= 0.5, "{fps}");
        }
    }

    #[test]
    fn changed_rectangle_bounds_every_difference() {
        let a = Image::new(10, 6);
        assert!(changed(&a, &a).is_none());
        let mut b = a.clone();
        b.pixels[2 * 10 + 7] = Ink::Left;
        b.pixels[4 * 10 + 3] = Ink::Right;
        let r = changed(&a, &b).unwrap();
        assert_eq!((r.x0, r.y0, r.x1, r.y1), (3, 2, 8, 5));
        b.pixels[9] = Ink::End;
        let r = changed(&a, &b).unwrap();
        assert_eq!((r.x0, r.y0, r.x1, r.y1), (3, 0, 10, 5));
    }

    #[test]
    fn grid_wraps_and_limits() {
        let opts = PreviewOptions {
            columns: 3,
            ..PreviewOptions::default()
        };
        let g = Grid::new(&opts, 8).unwrap();
        assert_eq!((g.columns, g.rows), (3, 3));
        assert_eq!(g.size(), (3 * 160 + 240, 3 * 240));
        assert_eq!(g.panel(4).x0, 160);
        assert_eq!(g.panel(4).y0, 240);
        let huge = PreviewOptions {
            panel_width: 4000,
            ..PreviewOptions::default()
        };
        assert!(Grid::new(&huge, 8).is_err());
    }
}
