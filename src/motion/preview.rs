//! Contact-sheet previews: a motion drawn as stick figures side by side, written as a PNG.
