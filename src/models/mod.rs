//! Denoiser networks, one file per architecture, named after its paper.
