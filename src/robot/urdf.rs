//! The URDF reader ([`parse`]): a robot description's text into its links and joints as the file
//! states them ([`Urdf`]), every value checked, in document order. The tree (one root, one parent
//! per link, no cycle, mimic sources, the floating base) is checked where it is built, in
//! [`super::model`].
//!
//! - **Read:** `<robot>`'s direct `<link>` and `<joint>` children. A link's name and its
//!   `<collision>` shapes (`box`, `cylinder`, `sphere`, `capsule` with their `<origin>`; a `mesh`
//!   is recorded as its file name and scale, never opened). A joint's name, type, parent and
//!   child links, `<origin xyz rpy>` (rpy fixed-axis: `R = Rz(y) · Ry(p) · Rx(r)`), `<axis>`
//!   (default `1 0 0`, normalised), `<limit lower upper velocity effort>` and `<mimic joint
//!   multiplier offset>`.
//! - **Ignored:** inertials, visuals, materials, transmissions, `<gazebo>` and other extensions,
//!   `<dynamics>`, `<calibration>`, `<safety_controller>`.
//! - **Checked** (each an [`crate::Error::InvalidArgument`] naming the element and its line):
//!   XML syntax, a root element other than `<robot>`, a DTD (refused, as entity expansion would
//!   be), missing or empty names, duplicate link or joint names, unknown joint types, a missing
//!   `<parent>`/`<child>`, malformed, non-finite or miscounted numbers, a zero axis on a joint
//!   that moves along it, a revolute or prismatic joint without `<limit>`, `lower > upper`,
//!   negative velocity or effort limits, negative shape sizes, a collision without a shape, and
//!   sizes: at most [`MAX_LINKS`] links, [`MAX_JOINTS`] joints and [`MAX_COLLISIONS`] collision
//!   shapes, counted before anything is stored, and [`MAX_XML_NODES`] XML nodes.
//! - **Defaults**, as urdfdom (ROS's reader) has them: a missing `<origin>` is the identity, a
//!   missing `lower`/`upper` is 0, a mimic's multiplier 1 and offset 0. Unlike urdfdom, a missing
//!   `velocity` or `effort` is "no limit" (+∞) rather than an error.

use super::pose::Pose;
use crate::error::{invalid_arg, Error, Result};
use crate::motion::rotation::Vec3;
use roxmltree::{Document, Node, ParsingOptions};
use std::collections::HashMap;

/// Most links a description may have (a humanoid with hands has about 70).
pub const MAX_LINKS: usize = 10_000;
/// Most joints a description may have.
pub const MAX_JOINTS: usize = 10_000;
/// Most `<collision>` elements in all.
pub const MAX_COLLISIONS: usize = 100_000;
/// Most XML nodes (elements, text, comments) the parser builds: a bound on its memory
/// (~100 MB) whatever the text. The 47 KB GR1T2 file has about 2,500.
pub const MAX_XML_NODES: u32 = 1_000_000;

/// A robot description as its file states it (document order, values checked, tree not yet).
#[derive(Clone, Debug, PartialEq)]
pub struct Urdf {
    /// `<robot name>` (empty when absent).
    pub name: String,
    /// The `<link>` children of `<robot>`, in document order; at least one, names unique.
    pub links: Vec<UrdfLink>,
    /// The `<joint>` children of `<robot>`, in document order (possibly none); names unique.
    pub joints: Vec<UrdfJoint>,
}

/// A `<link>`.
#[derive(Clone, Debug, PartialEq)]
pub struct UrdfLink {
    /// `<link name>`: not empty, unique among links; joints name links by it.
    pub name: String,
    /// The link's `<collision>` shapes, in document order (empty when it has none).
    pub collisions: Vec<Collision>,
}

/// A `<collision>`: a shape placed in its link's frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Collision {
    /// `<collision name>`, when given.
    pub name: Option<String>,
    /// `<origin>`: the shape's frame in the link's.
    pub origin: Pose,
    /// The shape, in the frame `origin` places.
    pub geometry: Geometry,
}

/// A collision shape, in its own frame (URDF's conventions: centred at the origin; cylinders and
/// capsules along z).
#[derive(Clone, Debug, PartialEq)]
pub enum Geometry {
    /// Full side lengths (x, y, z), metres.
    Box {
        /// Side lengths along x, y and z, metres (each ≥ 0).
        size: Vec3,
    },
    /// Radius and full length along z.
    Cylinder {
        /// Metres, ≥ 0.
        radius: f64,
        /// Full height along z, metres, ≥ 0.
        length: f64,
    },
    /// A ball centred at the origin.
    Sphere {
        /// Metres, ≥ 0.
        radius: f64,
    },
    /// Radius and length of the straight part along z (not a URDF standard shape; MuJoCo and
    /// Bullet read it).
    Capsule {
        /// Radius of the cylinder and of its two end caps, metres, ≥ 0.
        radius: f64,
        /// Length of the cylinder between the caps' centres, metres, ≥ 0 (the whole capsule
        /// is `length + 2 · radius` long).
        length: f64,
    },
    /// A mesh file, not read: its `filename` as written (often `package://…`) and `scale`.
    Mesh {
        /// The `filename` attribute, unresolved (a `package://` URI is not looked up).
        filename: String,
        /// Per-axis scale (x, y, z) of the mesh's vertices; `[1, 1, 1]` when absent.
        scale: Vec3,
    },
}

/// `<joint type>`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointType {
    /// `revolute`: rotation about `axis` between `<limit lower upper>`, radians.
    Revolute,
    /// `continuous`: rotation about `axis` without position limits.
    Continuous,
    /// `prismatic`: translation along `axis` between `<limit lower upper>`, metres.
    Prismatic,
    /// `fixed`: no motion; the child is rigidly at `origin`.
    Fixed,
    /// `floating`: six free degrees of freedom. [`crate::robot::Robot`] accepts it only as the
    /// joint from a `world` root (then the base pose places the child), never inside the tree.
    Floating,
    /// `planar`: motion in the plane normal to `axis`. Parsed, but refused by
    /// [`crate::robot::Robot`].
    Planar,
}

impl JointType {
    fn from_name(name: &str) -> Option<JointType> {
        Some(match name {
            "revolute" => JointType::Revolute,
            "continuous" => JointType::Continuous,
            "prismatic" => JointType::Prismatic,
            "fixed" => JointType::Fixed,
            "floating" => JointType::Floating,
            "planar" => JointType::Planar,
            _ => return None,
        })
    }

    /// The URDF name (`"revolute"`, …).
    pub fn name(self) -> &'static str {
        match self {
            JointType::Revolute => "revolute",
            JointType::Continuous => "continuous",
            JointType::Prismatic => "prismatic",
            JointType::Fixed => "fixed",
            JointType::Floating => "floating",
            JointType::Planar => "planar",
        }
    }

    /// Whether `<axis>` means something for this type (rotation or translation axis, plane
    /// normal): those refuse a zero axis.
    fn uses_axis(self) -> bool {
        !matches!(self, JointType::Fixed | JointType::Floating)
    }
}

/// `<limit>`: radians (revolute) or metres (prismatic), per second for `velocity`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limit {
    /// Lowest position (0 when absent); `lower ≤ upper` except on a continuous joint, whose
    /// `lower` and `upper` are not limits and are not checked.
    pub lower: f64,
    /// Highest position (0 when absent).
    pub upper: f64,
    /// +∞ when the file gives none.
    pub velocity: f64,
    /// +∞ when the file gives none.
    pub effort: f64,
}

/// `<mimic>`: this joint's position is `multiplier · q[joint] + offset`.
#[derive(Clone, Debug, PartialEq)]
pub struct Mimic {
    /// Name of the joint followed; [`crate::robot::Robot`] requires it to exist and to be
    /// revolute, continuous or prismatic.
    pub joint: String,
    /// Factor on the followed joint's position (1 when absent).
    pub multiplier: f64,
    /// Added after the product, radians or metres (0 when absent).
    pub offset: f64,
}

/// A `<joint>`.
#[derive(Clone, Debug, PartialEq)]
pub struct UrdfJoint {
    /// `<joint name>`: not empty, unique among joints; degrees of freedom are reported by it.
    pub name: String,
    /// `<joint type>`.
    pub kind: JointType,
    /// The parent link's name.
    pub parent: String,
    /// The child link's name.
    pub child: String,
    /// The joint frame in the parent link's frame (the child link's frame at q = 0).
    pub origin: Pose,
    /// Unit length for the types that use it; as written (possibly zero) for fixed and floating.
    pub axis: Vec3,
    /// `<limit>`: always present on revolute and prismatic joints (the parser requires it),
    /// optional on the others.
    pub limit: Option<Limit>,
    /// `<mimic>`, when this joint follows another instead of being a degree of freedom.
    pub mimic: Option<Mimic>,
    /// The line of `<joint>` in the file, for later errors about the tree.
    pub line: u32,
}

/// Reads a URDF document (module doc). Never panics.
pub fn parse(text: &str) -> Result<Urdf> {
    let options = ParsingOptions {
        allow_dtd: false,
        nodes_limit: MAX_XML_NODES,
        ..ParsingOptions::default()
    };
    let doc = Document::parse_with_options(text, options)
        .map_err(|e| invalid_arg!("URDF: not readable XML: {e}"))?;
    // Line numbers by binary search over the line starts: roxmltree's `text_pos_at` scans
    // the text from its start at every call, quadratic over a file's elements.
    let line_starts: Vec<usize> = std::iter::once(0)
        .chain(text.match_indices('\n').map(|(i, _)| i + 1))
        .collect();
    let at = |node: Node| line_starts.partition_point(|&s| s <= node.range().start) as u32;
    let robot = doc.root_element();
    if robot.tag_name().name() != "robot" {
        return Err(invalid_arg!(
            "URDF: the root element is <{}> (line {}), not <robot>",
            robot.tag_name().name(),
            at(robot)
        ));
    }
    let children = || robot.children().filter(|n| n.has_tag_name("link"));
    let joint_nodes = || robot.children().filter(|n| n.has_tag_name("joint"));
    let (n_links, n_joints) = (children().count(), joint_nodes().count());
    let n_collisions: usize = children()
        .map(|l| l.children().filter(|c| c.has_tag_name("collision")).count())
        .sum();
    if n_links > MAX_LINKS || n_joints > MAX_JOINTS || n_collisions > MAX_COLLISIONS {
        return Err(invalid_arg!(
            "URDF: {n_links} links, {n_joints} joints and {n_collisions} collision shapes; at most \
             {MAX_LINKS}, {MAX_JOINTS} and {MAX_COLLISIONS} are read"
        ));
    }
    if n_links == 0 {
        return Err(invalid_arg!(
            "URDF: <robot> (line {}) has no <link>",
            at(robot)
        ));
    }

    let mut links: Vec<UrdfLink> = Vec::with_capacity(n_links);
    let mut seen: HashMap<&str, u32> = HashMap::with_capacity(n_links);
    for node in children() {
        let link = read_link(node, &at)?;
        let name = node.attribute("name").unwrap_or_default();
        if let Some(first) = seen.insert(name, at(node)) {
            return Err(invalid_arg!(
                "URDF: two links are named `{}` (lines {first} and {})",
                link.name,
                at(node)
            ));
        }
        links.push(link);
    }
    let mut joints: Vec<UrdfJoint> = Vec::with_capacity(n_joints);
    seen.clear();
    for node in joint_nodes() {
        let joint = read_joint(node, &at)?;
        let name = node.attribute("name").unwrap_or_default();
        if let Some(first) = seen.insert(name, joint.line) {
            return Err(invalid_arg!(
                "URDF: two joints are named `{}` (lines {first} and {})",
                joint.name,
                joint.line
            ));
        }
        joints.push(joint);
    }
    Ok(Urdf {
        name: robot.attribute("name").unwrap_or_default().to_string(),
        links,
        joints,
    })
}

/// A `name` attribute that is present and not blank.
fn name_of(node: Node, what: &str, line: u32) -> Result<String> {
    match node.attribute("name") {
        Some(n) if !n.trim().is_empty() => Ok(n.to_string()),
        _ => Err(invalid_arg!("URDF: a <{what}> (line {line}) has no name")),
    }
}

fn read_link(node: Node, at: &dyn Fn(Node) -> u32) -> Result<UrdfLink> {
    let name = name_of(node, "link", at(node))?;
    let mut collisions = Vec::new();
    for c in node.children().filter(|c| c.has_tag_name("collision")) {
        let ctx = |what: String| invalid_arg!("URDF: link `{name}`: {what} (line {})", at(c));
        let origin = read_origin(c).map_err(|e| ctx(format!("collision <origin>: {e}")))?;
        let shape = c
            .children()
            .find(|g| g.has_tag_name("geometry"))
            .and_then(|g| g.children().find(Node::is_element))
            .ok_or_else(|| ctx("a <collision> without a <geometry> shape".into()))?;
        let geometry = read_geometry(shape).map_err(|e| ctx(format!("collision {e}")))?;
        collisions.push(Collision {
            name: c.attribute("name").map(str::to_string),
            origin,
            geometry,
        });
    }
    Ok(UrdfLink { name, collisions })
}

fn read_geometry(shape: Node) -> std::result::Result<Geometry, String> {
    let tag = shape.tag_name().name();
    let size = |attr: &str| -> std::result::Result<f64, String> {
        let v = required(shape, attr).and_then(|t| number(t, attr))?;
        if v < 0.0 {
            return Err(format!("<{tag} {attr}> is negative ({v})"));
        }
        Ok(v)
    };
    Ok(match tag {
        "box" => {
            let size: Vec3 = vector(required(shape, "size")?, "<box size>")?;
            if size.iter().any(|&v| v < 0.0) {
                return Err(format!("<box size> has a negative side ({size:?})"));
            }
            Geometry::Box { size }
        }
        "cylinder" => Geometry::Cylinder {
            radius: size("radius")?,
            length: size("length")?,
        },
        "capsule" => Geometry::Capsule {
            radius: size("radius")?,
            length: size("length")?,
        },
        "sphere" => Geometry::Sphere {
            radius: size("radius")?,
        },
        "mesh" => Geometry::Mesh {
            filename: required(shape, "filename")?.to_string(),
            scale: match shape.attribute("scale") {
                Some(s) => vector(s, "<mesh scale>")?,
                None => [1.0; 3],
            },
        },
        other => return Err(format!("shape <{other}> is not one URDF knows")),
    })
}

fn read_joint(node: Node, at: &dyn Fn(Node) -> u32) -> Result<UrdfJoint> {
    let line = at(node);
    let name = name_of(node, "joint", line)?;
    let err =
        |what: String| -> Error { invalid_arg!("URDF: joint `{name}` (line {line}): {what}") };
    let type_name = node
        .attribute("type")
        .ok_or_else(|| err("no type".into()))?;
    let kind = JointType::from_name(type_name).ok_or_else(|| {
        err(format!(
            "unknown type `{type_name}` (revolute, continuous, prismatic, fixed, floating, planar)"
        ))
    })?;
    let link_of = |tag: &str| -> Result<String> {
        let el = node
            .children()
            .find(|c| c.has_tag_name(tag))
            .ok_or_else(|| err(format!("no <{tag}>")))?;
        match el.attribute("link") {
            Some(l) if !l.trim().is_empty() => Ok(l.to_string()),
            _ => Err(err(format!("<{tag}> has no link"))),
        }
    };
    let (parent, child) = (link_of("parent")?, link_of("child")?);
    let origin = read_origin(node).map_err(|e| err(format!("<origin>: {e}")))?;

    let mut axis = [1.0, 0.0, 0.0];
    if let Some(a) = node.children().find(|c| c.has_tag_name("axis")) {
        let xyz = required(a, "xyz").map_err(|e| err(format!("<axis>: {e}")))?;
        axis = vector(xyz, "<axis xyz>").map_err(&err)?;
    }
    if kind.uses_axis() {
        let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
        // Below 1e-12 the direction is noise; an overflowing norm (|v| ~ 1e200) is not one.
        if !(n > 1e-12 && n.is_finite()) {
            return Err(err(format!(
                "the axis {axis:?} of a {} joint has no direction",
                kind.name()
            )));
        }
        axis = axis.map(|v| v / n);
    }

    let limit = match node.children().find(|c| c.has_tag_name("limit")) {
        Some(l) => Some(read_limit(l, kind).map_err(|e| err(format!("<limit>: {e}")))?),
        None if matches!(kind, JointType::Revolute | JointType::Prismatic) => {
            return Err(err(format!(
                "a {} joint needs a <limit> (lower, upper, velocity, effort)",
                kind.name()
            )))
        }
        None => None,
    };

    let mimic = match node.children().find(|c| c.has_tag_name("mimic")) {
        None => None,
        Some(m) => {
            let read = || -> std::result::Result<Mimic, String> {
                let joint = required(m, "joint")?.to_string();
                let opt = |attr: &str, default: f64| match m.attribute(attr) {
                    Some(t) => number(t, attr),
                    None => Ok(default),
                };
                Ok(Mimic {
                    joint,
                    multiplier: opt("multiplier", 1.0)?,
                    offset: opt("offset", 0.0)?,
                })
            };
            Some(read().map_err(|e| err(format!("<mimic>: {e}")))?)
        }
    };
    Ok(UrdfJoint {
        name: name.clone(),
        kind,
        parent,
        child,
        origin,
        axis,
        limit,
        mimic,
        line,
    })
}

fn read_limit(l: Node, kind: JointType) -> std::result::Result<Limit, String> {
    let opt = |attr: &str, default: f64| match l.attribute(attr) {
        Some(t) => number(t, attr),
        None => Ok(default),
    };
    let limit = Limit {
        lower: opt("lower", 0.0)?,
        upper: opt("upper", 0.0)?,
        velocity: opt("velocity", f64::INFINITY)?,
        effort: opt("effort", f64::INFINITY)?,
    };
    // A continuous joint's lower/upper mean nothing (urdfdom ignores them too).
    if kind != JointType::Continuous && limit.lower > limit.upper {
        return Err(format!(
            "lower {} is above upper {}",
            limit.lower, limit.upper
        ));
    }
    if limit.velocity < 0.0 || limit.effort < 0.0 {
        return Err(format!(
            "negative velocity ({}) or effort ({})",
            limit.velocity, limit.effort
        ));
    }
    Ok(limit)
}

/// The first `<origin>` child of `node` (identity when there is none).
fn read_origin(node: Node) -> std::result::Result<Pose, String> {
    let Some(o) = node.children().find(|c| c.has_tag_name("origin")) else {
        return Ok(Pose::IDENTITY);
    };
    let get = |attr: &str| match o.attribute(attr) {
        Some(t) => vector(t, attr),
        None => Ok([0.0; 3]),
    };
    Ok(Pose::from_xyz_rpy(get("xyz")?, get("rpy")?))
}

fn required<'a>(node: Node<'a, '_>, attr: &str) -> std::result::Result<&'a str, String> {
    node.attribute(attr)
        .ok_or_else(|| format!("<{}> has no `{attr}` attribute", node.tag_name().name()))
}

/// One finite number.
fn number(text: &str, what: &str) -> std::result::Result<f64, String> {
    let t = text.trim();
    match t.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("`{what}` is not finite (`{t}`)")),
        Err(_) => Err(format!("`{what}` is not a number (`{}`)", clip(t))),
    }
}

/// Exactly three finite numbers separated by white space.
fn vector(text: &str, what: &str) -> std::result::Result<Vec3, String> {
    let mut out = [0.0; 3];
    let mut n = 0;
    for token in text.split_whitespace() {
        if n < 3 {
            out[n] = number(token, what)?;
        }
        n += 1;
    }
    if n != 3 {
        return Err(format!(
            "`{what}` needs 3 numbers, has {n} (`{}`)",
            clip(text.trim())
        ));
    }
    Ok(out)
}

/// At most 40 characters of `text` for a message (a fuzzed attribute can be megabytes).
fn clip(text: &str) -> String {
    match text.char_indices().nth(40) {
        Some((i, _)) => format!("{}…", &text[..i]),
        None => text.to_string(),
    }
}
