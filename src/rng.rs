//! The in-crate seeded Gaussian generator.
