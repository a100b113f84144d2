//! Motion formats.
