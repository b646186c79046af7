//! gdrf-invert: not implemented yet; prints its help.
use clap::Parser;

/// Invert a photo into shape and appearance features (coming with the inversion issue).
#[derive(Parser)]
#[command(version, about, long_about = None)]
struct Args {}

fn main() {
    let _ = Args::parse();
    eprintln!("gdrf-invert is not implemented yet; see --help.");
    std::process::exit(2);
}
