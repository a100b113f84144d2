//! PLACEHOLDER (being written): analytic two-bone IK.
