//! `--robot`: a humanoid from its URDF. The URDF and its retarget configuration are read and
//! checked before any model is loaded, so a robot libflame cannot drive is refused before
//! minutes of sampling; the finished poses are retargeted onto it (`flame::robot`) and written
//! in the layout a robot-learning pipeline reads (`flame::robot::export`).
//!
//! Without `--retarget`, the configuration is `robots/<robot name, lower case>.json`, looked for
//! in this order: the current directory, the installation's share folder (`<prefix>/share/flame`
//! for an executable in `<prefix>/bin`), then the source tree this binary was built from (where
//! libflame ships gr1t2, jvrc1, g1 and h1). None found is an error naming every place tried.

use std::path::{Path, PathBuf};

use flame::motion::Poses;
use flame::robot::export::{self, RobotFile};
use flame::robot::{config, RetargetConfig, Retargeter, Robot, Trajectory};

use crate::args::OutputArgs;
use crate::paths;

/// A robot given with `--robot`, read, with its configuration and output file.
pub struct RobotOut {
    pub path: PathBuf,
    retargeter: Retargeter,
    pub file: RobotFile,
    header: bool,
}

impl RobotOut {
    /// The robot `o` names, or `None` (then no robot option may be given).
    pub fn new(o: &OutputArgs) -> Result<Option<RobotOut>, String> {
        let Some(path) = &o.robot else {
            for (given, flag) in [
                (o.retarget.is_some(), "--retarget"),
                (o.robot_format.is_some(), "--robot-format"),
                (o.csv_header, "--csv-header"),
            ] {
                if given {
                    return Err(format!("{flag} needs --robot (the robot's URDF)"));
                }
            }
            return Ok(None);
        };
        if o.rig.is_some() {
            return Err("--robot and --rig: give one target (a robot or a character)".into());
        }
        if let Some(layout) = o.amass {
            return Err(format!(
                "--amass {layout} writes the human's SMPL parameters; with --robot, --out is the \
                 robot's trajectory"
            ));
        }
        if let Some(c) = o.convention {
            return Err(format!(
                "--convention {c}: a robot trajectory is in the URDF's world (Z up, metres, \
                 radians); leave --convention out"
            ));
        }
        let ext = paths::extension(&o.out).unwrap_or_default();
        let file = RobotFile::for_extension(&ext, o.robot_format)
            .map_err(|e| format!("cannot write {}: {}", o.out.display(), plain(&e)))?;
        if o.csv_header && !file.is_csv() {
            return Err(format!(
                "--csv-header is for a .csv; --out {} holds its names inside",
                o.out.display()
            ));
        }
        paths::check_readable(path)?;
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        let robot = Robot::from_urdf(&text)
            .map_err(|e| format!("cannot read {}: {}", path.display(), plain(&e)))?;
        let (config_path, config) = read_config(o.retarget.as_deref(), &robot)?;
        let name = robot.name().to_string();
        let retargeter = Retargeter::new(robot, config)
            .map_err(|e| format!("cannot retarget onto {name}: {}", plain(&e)))?;
        eprintln!(
            "robot {name}: {} degrees of freedom, configuration {}",
            retargeter.robot().dof_count(),
            config_path.display()
        );
        Ok(Some(RobotOut {
            path: path.clone(),
            retargeter,
            file,
            header: o.csv_header,
        }))
    }

    /// `poses` (finished, at `fps`) on the robot, as the output file's bytes. The residual (how
    /// far the robot stayed from its targets) is summarised on stderr.
    pub fn file_bytes(&self, poses: &Poses, fps: f64) -> Result<Vec<u8>, String> {
        let traj = self.trajectory(poses, fps)?;
        export::to_bytes(&traj, self.retargeter.robot(), self.file, self.header)
            .map_err(|e| plain(&e))
    }

    fn trajectory(&self, poses: &Poses, fps: f64) -> Result<Trajectory, String> {
        let traj = self.retargeter.motion(poses, fps).map_err(|e| {
            format!(
                "cannot retarget onto {}: {}",
                self.path.display(),
                plain(&e)
            )
        })?;
        let mut r = traj.residual.clone();
        r.sort_by(f64::total_cmp);
        if let (Some(median), Some(max)) = (r.get(r.len() / 2), r.last()) {
            eprintln!(
                "retargeted {} frames onto {}: residual median {median:.4}, max {max:.4}",
                traj.frames(),
                self.retargeter.robot().name()
            );
        }
        Ok(traj)
    }
}

/// The error's message without the kind prefix the library puts on invalid arguments.
fn plain(e: &flame::Error) -> String {
    let m = e.to_string();
    m.strip_prefix("invalid argument: ")
        .map(str::to_string)
        .unwrap_or(m)
}

/// `--retarget FILE`, or the shipped configuration for `robot` (module doc).
fn read_config(given: Option<&Path>, robot: &Robot) -> Result<(PathBuf, RetargetConfig), String> {
    let path = match given {
        Some(p) => {
            paths::check_readable(p)?;
            p.to_path_buf()
        }
        None => {
            let tried: Vec<PathBuf> = config_dirs()
                .iter()
                .map(|d| config::default_config_path(robot, d))
                .collect();
            match tried.iter().find(|p| p.is_file()) {
                Some(p) => p.clone(),
                None => {
                    let list: Vec<String> = tried.iter().map(|p| p.display().to_string()).collect();
                    return Err(format!(
                        "no retarget configuration for robot `{}`: give --retarget FILE.json \
                         (tried {})",
                        robot.name(),
                        list.join(", ")
                    ));
                }
            }
        }
    };
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let config = RetargetConfig::from_json(&text, robot)
        .map_err(|e| format!("cannot use {}: {}", path.display(), plain(&e)))?;
    Ok((path, config))
}

/// Where shipped configurations are looked for, in order (module doc).
fn config_dirs() -> Vec<PathBuf> {
    let mut dirs = vec![PathBuf::from("robots")];
    if let Some(prefix) = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent()?.parent().map(Path::to_path_buf))
    {
        dirs.push(prefix.join("share").join("flame").join("robots"));
    }
    dirs.push(Path::new(env!("CARGO_MANIFEST_DIR")).join("robots"));
    dirs
}
