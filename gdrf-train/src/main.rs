//! gdrf-train: not implemented yet; prints its help.
use clap::Parser;

/// Train a GDRF generator on an image collection (coming with the training issue).
#[derive(Parser)]
#[command(version, about, long_about = None)]
struct Args {}

fn main() {
    let _ = Args::parse();
    eprintln!("gdrf-train is not implemented yet; see --help.");
    std::process::exit(2);
}
