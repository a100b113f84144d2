//! Assembling a complete model file from a denoiser-only file and a text encoder shipped
//! elsewhere (the demo model: its denoiser lives in the repository, all-MiniLM-L6-v2 comes from
//! the package registry at set-up).
