//! The demo model's data side: a seeded procedural motion corpus on the SMPL-24 skeleton
//! (`smpl24_6d`, 20 fps) with many-worded descriptions, and a rule-based action classifier over
//! joint positions that checks both the corpus and what the trained demo model generates.
//!
//! - [`rig`]: per-frame controls → SMPL-24 rotations (analytic two-bone IK) → features.
//! - [`actions`]: one generator per action family, all starting and ending in the neutral stance.
//! - [`sentences`]: template descriptions.
//! - [`corpus`]: whole motions (one action or two in sequence), files on disk.
//! - [`classify`]: the rule-based classifier.
//!
//! `docs/demo_corpus.md` documents the families, variations, vocabulary, rules and accuracy.
//!
//! A crate of its own beside the runtime (`flame`): the tests, the `flame-corpus` tool and the
//! demo training scripts use it; the libraries engines link (`libflame.so`, `libflame.a`) do not
//! carry it.

pub mod actions;
pub mod classify;
pub mod corpus;
pub mod family;
pub mod rig;
pub mod sentences;

pub use family::Family;

/// Result of judging motions against their intended families: counts per (intended, predicted).
#[derive(Clone, Debug, Default)]
pub struct Confusion {
    /// `counts[intended][predicted]`, indexed by [`Family::index`].
    pub counts: [[usize; 15]; 15],
}

impl Confusion {
    pub fn add(&mut self, intended: Family, predicted: Family) {
        self.counts[intended.index()][predicted.index()] += 1;
    }

    pub fn total(&self) -> usize {
        self.counts.iter().flatten().sum()
    }

    pub fn correct(&self) -> usize {
        (0..15).map(|i| self.counts[i][i]).sum()
    }

    /// Correct / total (0 when empty).
    pub fn accuracy(&self) -> f64 {
        self.correct() as f64 / self.total().max(1) as f64
    }

    /// A fixed-width table: rows intended, columns predicted (first four letters of the name).
    pub fn table(&self) -> String {
        let mut s = format!("{:>11}", "intended");
        for f in Family::ALL {
            s.push_str(&format!(" {:>5}", &f.name()[..4.min(f.name().len())]));
        }
        s.push_str("   acc\n");
        for a in Family::ALL {
            let row = &self.counts[a.index()];
            let n: usize = row.iter().sum();
            s.push_str(&format!("{:>11}", a.name()));
            for c in row {
                s.push_str(&format!(" {c:>5}"));
            }
            let acc = row[a.index()] as f64 / n.max(1) as f64;
            s.push_str(&format!(" {:>5.1}\n", 100.0 * acc));
        }
        s
    }
}
