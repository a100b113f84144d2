//! The action families of the demo corpus: stable lowercase names shared by the corpus files,
//! the classifier and the evaluation prompts.

use std::fmt;

/// One action family. The integer order is the order of [`Family::ALL`] (and of the confusion
/// table rows); names never change once a corpus has been written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Family {
    Walk,
    Run,
    Jump,
    Hop,
    Wave,
    Clap,
    Punch,
    Kick,
    Squat,
    Crouch,
    Turn,
    RaiseArms,
    Bow,
    SideStep,
    Stand,
}

impl Family {
    /// Every family, in table order.
    pub const ALL: [Family; 15] = [
        Family::Walk,
        Family::Run,
        Family::Jump,
        Family::Hop,
        Family::Wave,
        Family::Clap,
        Family::Punch,
        Family::Kick,
        Family::Squat,
        Family::Crouch,
        Family::Turn,
        Family::RaiseArms,
        Family::Bow,
        Family::SideStep,
        Family::Stand,
    ];

    /// The stable lowercase name (`walk`, `raise_arms`, `side_step`, …).
    pub fn name(self) -> &'static str {
        match self {
            Family::Walk => "walk",
            Family::Run => "run",
            Family::Jump => "jump",
            Family::Hop => "hop",
            Family::Wave => "wave",
            Family::Clap => "clap",
            Family::Punch => "punch",
            Family::Kick => "kick",
            Family::Squat => "squat",
            Family::Crouch => "crouch",
            Family::Turn => "turn",
            Family::RaiseArms => "raise_arms",
            Family::Bow => "bow",
            Family::SideStep => "side_step",
            Family::Stand => "stand",
        }
    }

    /// The family called `name`, if any.
    pub fn from_name(name: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Position in [`Family::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Family {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_in_table_order() {
        for (i, f) in Family::ALL.into_iter().enumerate() {
            assert_eq!(f.index(), i);
            assert_eq!(Family::from_name(f.name()), Some(f));
        }
        assert_eq!(Family::from_name("dance"), None);
    }
}
