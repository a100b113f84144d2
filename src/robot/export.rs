//! The files robot-learning pipelines read, written from a [`Trajectory`]. Nothing here retargets
//! or reads files; every writer gives the file's bytes.
//!
//! - **BeyondMimic's CSV** ([`beyondmimic_csv`]): one row per frame, `x, y, z, qx, qy, qz, qw,
//!   q_1 … q_n`: base position (metres), base quaternion **x, y, z, w**, then the joint positions
//!   in the order of [`Trajectory::dof_names`]. HybridRobotics/whole_body_tracking
//!   (`scripts/csv_to_npz.py`, `MotionLoader._load_motion`) reads it with
//!   `np.loadtxt(file, delimiter=",")`, headerless. The optional header is one line of column
//!   names starting with `# `, a comment to `np.loadtxt` (so that reader still takes the file;
//!   its `--frame_range` then counts the header line as line 1).
//! - **GMR's fields** ([`gmr_npz`]): YanjieZe/GMR (`scripts/smplx_to_robot.py`) pickles `fps`,
//!   `root_pos` [N, 3], `root_rot` [N, 4] **x, y, z, w**, `dof_pos` [N, n], `local_body_pos` and
//!   `link_body_list`. Written here as an `.npz` (every array `float64`, `fps` a 0-d array) with
//!   `joint_names`, the columns of `dof_pos` (a 1-D unicode array, `np.array(names)`).
//!   `local_body_pos` and `link_body_list` are `None` in GMR's own files: they are left out, as
//!   an `.npz` holds arrays only. GMR's `dof_pos` follows its MuJoCo model's `qpos`; this one
//!   follows `joint_names` (the URDF's document order, which is MuJoCo's when the file lists its
//!   joints depth first, as GR1T2's and JVRC-1's do).
//! - **MuJoCo qpos** ([`qpos_wxyz`], [`qpos_csv`], [`qpos_npy`]): per frame the free joint's
//!   `x, y, z, qw, qx, qy, qz` (quaternion **w first**, MuJoCo's) then one value per hinge or
//!   slide in MuJoCo's order of a compiled URDF ([`Robot::mujoco_joint_order`]), mimic joints
//!   included at their mimicked position (MuJoCo makes them independent joints). nv-tlabs/kimodo
//!   (`kimodo/exports/mujoco.py`) writes its G1 motions as such rows. As a CSV (optional `# `
//!   header: `x,y,z,qw,qx,qy,qz,` and the joint names) or an `.npy` `[N, 7 + joints]` `float64`.
//!
//! Numbers in CSVs are written in the shortest form that reads back to the same `f64`
//! (exponent form outside 1e-4 ≤ |v| < 1e15), so a file read back holds the trajectory exactly.

use std::fmt::{self, Write as _};
use std::str::FromStr;

use super::model::Robot;
use super::trajectory::Trajectory;
use crate::error::{invalid_arg, Error, Result};
use crate::npz::Npz;

/// Which pipeline's layout a trajectory is written in (`--robot-format`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RobotFormat {
    /// BeyondMimic's CSV rows (base quaternion x, y, z, w).
    BeyondMimic,
    /// GMR's fields (`root_rot` x, y, z, w) in an `.npz`.
    Gmr,
    /// MuJoCo qpos rows (base quaternion w, x, y, z).
    Qpos,
}

impl RobotFormat {
    /// Every format; [`FromStr`] looks a name up among them.
    pub const ALL: [RobotFormat; 3] = [
        RobotFormat::BeyondMimic,
        RobotFormat::Gmr,
        RobotFormat::Qpos,
    ];

    /// `beyondmimic`, `gmr` or `qpos`, as `FromStr` and the CLI take them.
    pub fn name(self) -> &'static str {
        match self {
            RobotFormat::BeyondMimic => "beyondmimic",
            RobotFormat::Gmr => "gmr",
            RobotFormat::Qpos => "qpos",
        }
    }
}

impl FromStr for RobotFormat {
    type Err = Error;
    fn from_str(s: &str) -> Result<RobotFormat> {
        RobotFormat::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| {
                invalid_arg!("unknown robot format `{s}` (expected beyondmimic, gmr or qpos)")
            })
    }
}

impl fmt::Display for RobotFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// One robot trajectory file: a layout in a container. The C ABI's `FLAME_ROBOT_*` values are
/// the discriminants.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum RobotFile {
    /// [`beyondmimic_csv`]: `x, y, z, qx, qy, qz, qw, q_1 … q_n`.
    BeyondMimicCsv = 0,
    /// [`gmr_npz`]: `fps`, `root_pos`, `root_rot` (x, y, z, w), `dof_pos`, `joint_names`.
    GmrNpz = 1,
    /// [`qpos_csv`]: `x, y, z, qw, qx, qy, qz`, joints in MuJoCo's order.
    QposCsv = 2,
    /// [`qpos_npy`]: the same rows as a `[N, 7 + joints]` array.
    QposNpy = 3,
}

impl RobotFile {
    /// The file with C ABI value `v`.
    pub fn from_u32(v: u32) -> Result<RobotFile> {
        Ok(match v {
            0 => RobotFile::BeyondMimicCsv,
            1 => RobotFile::GmrNpz,
            2 => RobotFile::QposCsv,
            3 => RobotFile::QposNpy,
            _ => {
                return Err(invalid_arg!(
                    "unknown robot trajectory file {v} (0 BeyondMimic CSV, 1 GMR .npz, 2 qpos \
                     CSV, 3 qpos .npy)"
                ))
            }
        })
    }

    /// The file for an output ending in `extension` (lower case, no dot), in `format` or, when
    /// none is given, the one the extension implies (`.csv` BeyondMimic, `.npz` GMR, `.npy`
    /// qpos). A format the container cannot hold is an error saying which ones can.
    pub fn for_extension(extension: &str, format: Option<RobotFormat>) -> Result<RobotFile> {
        use RobotFormat::*;
        match (extension, format) {
            ("csv", None | Some(BeyondMimic)) => Ok(RobotFile::BeyondMimicCsv),
            ("csv", Some(Qpos)) => Ok(RobotFile::QposCsv),
            ("npz", None | Some(Gmr)) => Ok(RobotFile::GmrNpz),
            ("npy", None | Some(Qpos)) => Ok(RobotFile::QposNpy),
            (e @ ("csv" | "npz" | "npy"), Some(f)) => Err(invalid_arg!(
                "a .{e} cannot hold the {f} layout (beyondmimic: .csv; gmr: .npz; qpos: .csv or \
                 .npy)"
            )),
            (e, _) => Err(invalid_arg!(
                "a robot trajectory is written as .csv (BeyondMimic's rows, or qpos), .npz \
                 (GMR's fields) or .npy (qpos), not .{e}"
            )),
        }
    }

    /// Whether the file is text with an optional header line.
    pub fn is_csv(self) -> bool {
        matches!(self, RobotFile::BeyondMimicCsv | RobotFile::QposCsv)
    }
}

/// `traj` as `file`'s bytes (`header`: the CSVs' column-name line; refused for the others).
/// `robot` is needed for the qpos files (MuJoCo's joint order, mimic joints) and checked against
/// the trajectory's degrees of freedom.
pub fn to_bytes(
    traj: &Trajectory,
    robot: &Robot,
    file: RobotFile,
    header: bool,
) -> Result<Vec<u8>> {
    if header && !file.is_csv() {
        return Err(invalid_arg!(
            "a header line is for the CSV files; {file:?} has its names inside"
        ));
    }
    check_robot(traj, robot)?;
    match file {
        RobotFile::BeyondMimicCsv => beyondmimic_csv(traj, header).map(String::into_bytes),
        RobotFile::GmrNpz => gmr_npz(traj),
        RobotFile::QposCsv => qpos_csv(traj, robot, header).map(String::into_bytes),
        RobotFile::QposNpy => qpos_npy(traj, robot),
    }
}

/// BeyondMimic's CSV (module doc), one line per frame, `\n`-terminated.
pub fn beyondmimic_csv(traj: &Trajectory, header: bool) -> Result<String> {
    check(traj)?;
    let mut out = String::with_capacity(csv_capacity(traj.frames(), 7 + traj.dofs()));
    if header {
        let names = ["x", "y", "z", "qx", "qy", "qz", "qw"]
            .into_iter()
            .chain(traj.dof_names.iter().map(String::as_str));
        header_line(&mut out, names)?;
    }
    for t in 0..traj.frames() {
        let row = traj.root_pos[t]
            .iter()
            .chain(&traj.root_rot_xyzw[t])
            .chain(traj.dof_row(t));
        csv_row(&mut out, row.copied());
    }
    Ok(out)
}

/// GMR's fields as an `.npz` (module doc).
pub fn gmr_npz(traj: &Trajectory) -> Result<Vec<u8>> {
    check(traj)?;
    let (frames, dofs) = (traj.frames(), traj.dofs());
    let mut z = Npz::new();
    z.add_scalar_f64("fps", traj.fps)?;
    let root_pos: Vec<f64> = traj.root_pos.iter().flatten().copied().collect();
    z.add_f64("root_pos", &[frames, 3], &root_pos)?;
    let root_rot: Vec<f64> = traj.root_rot_xyzw.iter().flatten().copied().collect();
    z.add_f64("root_rot", &[frames, 4], &root_rot)?;
    z.add_f64("dof_pos", &[frames, dofs], &traj.dof_pos)?;
    let names: Vec<&str> = traj.dof_names.iter().map(String::as_str).collect();
    z.add_strs("joint_names", &names)?;
    Ok(z.finish())
}

/// MuJoCo's `qpos` width for `robot`: the free joint's 7 then one per hinge or slide.
pub fn qpos_width(robot: &Robot) -> usize {
    7 + robot.mujoco_joint_order().len()
}

/// The qpos columns' names: `x, y, z, qw, qx, qy, qz`, then the joints in MuJoCo's order.
pub fn qpos_names(robot: &Robot) -> Vec<String> {
    ["x", "y", "z", "qw", "qx", "qy", "qz"]
        .into_iter()
        .map(str::to_string)
        .chain(
            robot
                .mujoco_joint_order()
                .iter()
                .map(|&j| robot.joints()[j].name.clone()),
        )
        .collect()
}

/// The trajectory as MuJoCo qpos rows (module doc), row-major `frames × qpos_width(robot)`.
pub fn qpos_wxyz(traj: &Trajectory, robot: &Robot) -> Result<Vec<f64>> {
    check(traj)?;
    check_robot(traj, robot)?;
    let width = qpos_width(robot);
    let mut out = Vec::with_capacity(traj.frames() * width);
    for t in 0..traj.frames() {
        let [x, y, z, w] = traj.root_rot_xyzw[t];
        out.extend_from_slice(&traj.root_pos[t]);
        out.extend_from_slice(&[w, x, y, z]);
        let q = traj.dof_row(t);
        out.extend(
            robot
                .mujoco_joint_order()
                .iter()
                .map(|&j| robot.joint_position(j, q)),
        );
    }
    Ok(out)
}

/// MuJoCo qpos rows as a CSV (`header`: `# x,y,z,qw,qx,qy,qz,<joints>`).
pub fn qpos_csv(traj: &Trajectory, robot: &Robot, header: bool) -> Result<String> {
    let rows = qpos_wxyz(traj, robot)?;
    let width = qpos_width(robot);
    let mut out = String::with_capacity(csv_capacity(traj.frames(), width));
    if header {
        let names = qpos_names(robot);
        header_line(&mut out, names.iter().map(String::as_str))?;
    }
    for row in rows.chunks_exact(width) {
        csv_row(&mut out, row.iter().copied());
    }
    Ok(out)
}

/// MuJoCo qpos rows as an `.npy` `[frames, qpos_width(robot)]` of `float64`.
pub fn qpos_npy(traj: &Trajectory, robot: &Robot) -> Result<Vec<u8>> {
    let rows = qpos_wxyz(traj, robot)?;
    crate::npy::encode_f64(&[traj.frames(), qpos_width(robot)], &rows)
}

/// A trajectory every writer can take: consistent, finite, at least one frame.
fn check(traj: &Trajectory) -> Result<()> {
    traj.validate()?;
    if traj.frames() == 0 {
        return Err(invalid_arg!("the trajectory has no frames"));
    }
    Ok(())
}

/// The trajectory's columns must be `robot`'s degrees of freedom.
fn check_robot(traj: &Trajectory, robot: &Robot) -> Result<()> {
    if traj.dof_names != robot.dof_names() {
        return Err(invalid_arg!(
            "the trajectory's {} degrees of freedom are not robot `{}`'s {}",
            traj.dofs(),
            robot.name(),
            robot.dof_count()
        ));
    }
    Ok(())
}

/// Room for `frames` rows of `cols` numbers of about 20 characters.
fn csv_capacity(frames: usize, cols: usize) -> usize {
    frames.saturating_mul(cols).saturating_mul(20)
}

/// `# a,b,c\n`. A name holding a comma, quote or line break would shift or break the columns.
fn header_line<'a>(out: &mut String, names: impl Iterator<Item = &'a str>) -> Result<()> {
    out.push_str("# ");
    for (i, name) in names.enumerate() {
        if name.contains([',', '"', '\n', '\r']) {
            return Err(invalid_arg!(
                "joint name {name:?} holds a comma, quote or line break: no CSV header can \
                 name it (write the file without one)"
            ));
        }
        if i > 0 {
            out.push(',');
        }
        out.push_str(name);
    }
    out.push('\n');
    Ok(())
}

fn csv_row(out: &mut String, values: impl Iterator<Item = f64>) {
    for (i, v) in values.enumerate() {
        if i > 0 {
            out.push(',');
        }
        push_number(out, v);
    }
    out.push('\n');
}

/// The shortest text that reads back to `v` (Rust's `Display`/`LowerExp` are exact round trips),
/// in exponent form when plain decimals would be long.
fn push_number(out: &mut String, v: f64) {
    let a = v.abs();
    // Writing into a String cannot fail.
    if a == 0.0 || (1e-4..1e15).contains(&a) {
        let _ = write!(out, "{v}");
    } else {
        let _ = write!(out, "{v:e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two degrees of freedom, `yaw` then `slide` in document order, and `follow` mimicking
    /// `yaw` (× 2, + 0.1) on `yaw`'s child but listed last: MuJoCo's depth-first order is
    /// `yaw, follow, slide`.
    fn robot() -> Robot {
        Robot::from_urdf(
            r#"<robot name="toy">
              <link name="base"/><link name="a"/><link name="b"/><link name="c"/>
              <joint name="yaw" type="revolute"><parent link="base"/><child link="a"/>
                <axis xyz="0 0 1"/><limit lower="-1" upper="1" velocity="1" effort="1"/></joint>
              <joint name="slide" type="prismatic"><parent link="base"/><child link="c"/>
                <axis xyz="1 0 0"/><limit lower="0" upper="1" velocity="1" effort="1"/></joint>
              <joint name="follow" type="revolute"><parent link="a"/><child link="b"/>
                <axis xyz="0 1 0"/><limit lower="-3" upper="3" velocity="1" effort="1"/>
                <mimic joint="yaw" multiplier="2" offset="0.1"/></joint>
            </robot>"#,
        )
        .unwrap()
    }

    /// Two frames; the rotation of frame 1 is a quarter turn about z (x, y, z, w =
    /// 0, 0, sin 45°, cos 45°).
    fn traj() -> Trajectory {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        Trajectory {
            fps: 30.0,
            robot: "toy".into(),
            dof_names: vec!["yaw".into(), "slide".into()],
            root_pos: vec![[0.0, 0.0, 0.9], [0.1, -0.25, 0.875]],
            root_rot_xyzw: vec![[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, h, h]],
            dof_pos: vec![0.5, 0.25, -1.0, 1e-7],
            residual: vec![0.0, 0.01],
        }
    }

    #[test]
    fn the_toy_robot_orders_its_joints_two_ways() {
        let r = robot();
        assert_eq!(r.dof_names(), ["yaw", "slide"]);
        let order: Vec<&str> = r
            .mujoco_joint_order()
            .iter()
            .map(|&j| r.joints()[j].name.as_str())
            .collect();
        assert_eq!(order, ["yaw", "follow", "slide"]);
    }

    #[test]
    fn beyondmimic_rows_are_position_xyzw_then_dofs() {
        let csv = beyondmimic_csv(&traj(), false).unwrap();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert_eq!(
            csv,
            format!("0,0,0.9,0,0,0,1,0.5,0.25\n0.1,-0.25,0.875,0,0,{h},{h},-1,1e-7\n")
        );
        let with = beyondmimic_csv(&traj(), true).unwrap();
        assert_eq!(with.lines().next(), Some("# x,y,z,qx,qy,qz,qw,yaw,slide"));
        assert_eq!(&with[with.find('\n').unwrap() + 1..], csv);
    }

    #[test]
    fn numbers_read_back_exactly() {
        let mut s = String::new();
        for v in [
            0.1,
            -0.0,
            1.0 / 3.0,
            123456.789,
            1e-5,
            2.5e20,
            -7e-300,
            f64::MIN_POSITIVE,
        ] {
            s.clear();
            push_number(&mut s, v);
            assert_eq!(s.parse::<f64>().unwrap().to_bits(), v.to_bits(), "{s}");
            assert!(s.len() <= 24, "{s}");
        }
    }

    #[test]
    fn qpos_is_w_first_in_mujoco_order_with_the_mimic() {
        let (r, t) = (robot(), traj());
        assert_eq!(qpos_width(&r), 10);
        let q = qpos_wxyz(&t, &r).unwrap();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        // follow = 2 · yaw + 0.1: 1.1 then -1.9.
        assert_eq!(
            q,
            [
                0.0, 0.0, 0.9, 1.0, 0.0, 0.0, 0.0, 0.5, 1.1, 0.25, //
                0.1, -0.25, 0.875, h, 0.0, 0.0, h, -1.0, -1.9, 1e-7
            ]
        );
        let csv = qpos_csv(&t, &r, true).unwrap();
        let mut lines = csv.lines();
        assert_eq!(lines.next(), Some("# x,y,z,qw,qx,qy,qz,yaw,follow,slide"));
        assert_eq!(lines.next(), Some("0,0,0.9,1,0,0,0,0.5,1.1,0.25"));
        let npy = qpos_npy(&t, &r).unwrap();
        let (shape, values) = crate::npy::decode_f32(&npy).unwrap();
        assert_eq!(shape, [2, 10]);
        assert_eq!(values[18], -1.9f32);
        assert_eq!(&npy[npy.len() - 8..], &1e-7f64.to_le_bytes());
    }

    #[test]
    fn gmr_npz_holds_the_fields_in_float64() {
        let bytes = gmr_npz(&traj()).unwrap();
        for header in [
            "{'descr': '<f8', 'fortran_order': False, 'shape': (), }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 4), }",
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 2), }",
            "{'descr': '<U5', 'fortran_order': False, 'shape': (2,), }",
        ] {
            let h = header.as_bytes();
            assert!(bytes.windows(h.len()).any(|w| w == h), "{header}");
        }
        for name in [
            "fps.npy",
            "root_pos.npy",
            "root_rot.npy",
            "dof_pos.npy",
            "joint_names.npy",
        ] {
            assert!(bytes.windows(name.len()).any(|w| w == name.as_bytes()));
        }
        // root_rot of frame 1 is x, y, z, w: its w (cos 45°) is the last of the 8 values.
        let h = std::f64::consts::FRAC_1_SQRT_2.to_le_bytes();
        let rot = b"{'descr': '<f8', 'fortran_order': False, 'shape': (2, 4), }";
        let at = bytes.windows(rot.len()).position(|w| w == rot).unwrap();
        let data = at + u16::from_le_bytes([bytes[at - 2], bytes[at - 1]]) as usize;
        assert_eq!(&bytes[data + 48..data + 56], &h);
        assert_eq!(&bytes[data + 56..data + 64], &h);
        assert_eq!(&bytes[data + 24..data + 32], &1.0f64.to_le_bytes());
    }

    #[test]
    fn files_follow_extension_and_format() {
        use RobotFormat::*;
        let f = RobotFile::for_extension;
        assert_eq!(f("csv", None).unwrap(), RobotFile::BeyondMimicCsv);
        assert_eq!(f("csv", Some(Qpos)).unwrap(), RobotFile::QposCsv);
        assert_eq!(f("npz", None).unwrap(), RobotFile::GmrNpz);
        assert_eq!(f("npy", None).unwrap(), RobotFile::QposNpy);
        let e = f("npz", Some(BeyondMimic)).unwrap_err().to_string();
        assert!(e.contains("cannot hold the beyondmimic layout"), "{e}");
        assert!(f("bvh", None).is_err());
        assert_eq!("gmr".parse::<RobotFormat>().unwrap(), Gmr);
        assert!("GMR".parse::<RobotFormat>().is_err());
        for v in 0..4 {
            assert_eq!(RobotFile::from_u32(v).unwrap() as u32, v);
        }
        assert!(RobotFile::from_u32(4).is_err());
    }

    #[test]
    fn bad_trajectories_are_errors() {
        let r = robot();
        let mut t = traj();
        t.dof_pos[1] = f64::NAN;
        assert!(beyondmimic_csv(&t, false).is_err());
        let mut t = traj();
        t.dof_pos.pop();
        assert!(gmr_npz(&t).is_err());
        let mut t = traj();
        t.dof_names.swap(0, 1);
        let e = qpos_wxyz(&t, &r).unwrap_err().to_string();
        assert!(e.contains("not robot `toy`'s 2"), "{e}");
        let mut t = traj();
        t.root_pos.clear();
        t.root_rot_xyzw.clear();
        t.dof_pos.clear();
        t.residual.clear();
        assert!(beyondmimic_csv(&t, false)
            .unwrap_err()
            .to_string()
            .contains("no frames"));
        let mut t = traj();
        t.dof_names[0] = "a,b".into();
        assert!(beyondmimic_csv(&t, true).is_err());
        assert!(beyondmimic_csv(&t, false).is_ok());
        assert!(to_bytes(&traj(), &r, RobotFile::GmrNpz, true).is_err());
        assert!(to_bytes(&traj(), &r, RobotFile::QposNpy, false).is_ok());
    }
}
