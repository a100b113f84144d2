//! `flame-corpus`: writes the procedural demo corpus and classifies motions (see `flame::demo`).

fn main() {
    eprintln!("flame-corpus: not built yet");
    std::process::exit(2);
}
