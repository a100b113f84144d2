//! Contact-sheet previews: a motion drawn as stick figures side by side, written as a PNG.
//! Nothing here reads or writes motion data; the drawing, the PNG chunks and their CRCs are
//! ours, only zlib compression comes from `miniz_oxide` (the `preview` feature).
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

/// The colours of a sheet; the discriminant is the PNG palette index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Ink {
    Background = 0,
    /// Panel separators and the path panel's grid.
    Border = 1,
    Ground = 2,
    /// Bones and joints whose joint name starts with `L_` / `left_`.
    Left = 3,
    /// … `R_` / `right_`.
    Right = 4,
    /// Pelvis, spine, neck and head.
    Spine = 5,
    Path = 6,
    /// The drawn frames' pelvis positions on the path.
    Sample = 7,
    Start = 8,
    End = 9,
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

    pub fn width(&self) -> u32 {
        self.width
    }

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
    let figures = Figures::new(poses, &view, &frames, &grid);
    for (i, &t) in frames.iter().enumerate() {
        let panel = grid.panel(i);
        figures.draw(&mut img, panel, t);
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
    fn new(poses: &'a Poses, view: &'a View, frames: &[usize], grid: &Grid) -> Figures<'a> {
        let skel = poses.format().skeleton();
        let joints = skel.joint_count();
        let (w, h) = (f64::from(grid.panel_w), f64::from(grid.panel_h));
        let ground_row = grid.panel_h - grid.panel_h / 10;
        let top = f64::from(grid.panel_h / 10);
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

    /// Ground line, then bones far to near, each with a disc on its joint and the head's ring.
    fn draw(&self, img: &mut Image, panel: Rect, t: usize) {
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
    let mid = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    // On a pixel centre, so a level path is an odd number of rows thick, not jagged.
    let centre = [
        f64::from(panel.x0 + panel.x1 / 2 - panel.x0 / 2) + 0.5,
        f64::from(panel.y0 + panel.y1 / 2 - panel.y0 / 2) + 0.5,
    ];
    let screen = |r: &[f64; 2]| {
        [
            centre[0] + (r[0] - mid[0]) * scale,
            centre[1] - (r[1] - mid[1]) * scale,
        ]
    };
    draw_grid(img, panel, centre, scale);
    let line = (panel.height().min(panel.width()) / 160.0).max(1.0);
    for pair in root.windows(2) {
        img.capsule(panel, screen(&pair[0]), screen(&pair[1]), line, Ink::Path);
    }
    for &t in frames {
        img.disc(panel, screen(&root[t]), line + 1.5, Ink::Sample);
    }
    img.disc(panel, screen(&root[0]), line + 3.0, Ink::Start);
    img.disc(panel, screen(&root[root.len() - 1]), line + 3.0, Ink::End);
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
