"""PyTorch references of the official models and samplers (oracles for the Rust parity tests)."""
