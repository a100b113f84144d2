//! The demo model's data side: a seeded procedural motion corpus on the SMPL-24 skeleton
//! (`smpl24_6d`, 20 fps) with many-worded descriptions, and a rule-based action classifier over
//! joint positions that checks both the corpus and what the trained demo model generates.
