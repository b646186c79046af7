//! gdrf-invert: a photo into shape and appearance features (paper §5), written as the
//! feature file gdrf-edit reads. The commands live in gdrf_core::invert::command and
//! gdrf_core::bench::invert.
use clap::Parser;
use gdrf_core::invert::command::{self, Options, TrainInitOptions};

/// Invert a photo into GDRF shape and appearance features.
///
/// Renders the generator at the photo's pose and optimises the shape feature w_s and the
/// appearance modulation (γ_a, β_a) with Adam on MSE + a perceptual distance + priors that
/// keep them near their start (paper §5). Writes into --out: features.safetensors (for
/// `gdrf-edit --shape-from/--appearance-from`), input.png (the photo as compared),
/// reconstruction.png, compare.png (photo | start | result), an orbit of novel views
/// (orbit/frame-NNN.png and orbit.gif), loss.png and invert.json (settings, timings and
/// the loss of every step).
///
/// `gdrf-invert train-init` trains the initialiser (--init) for a generator.
#[derive(Parser)]
#[command(version, about, long_about, args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    invert: Options,
}

#[derive(clap::Subcommand)]
enum Command {
    /// Train the initialiser F (ResNet-34 from scratch, paper §5.2) on images the generator
    /// renders: it predicts w_s and the camera pose of a photo. Writes --out atomically at
    /// every validation and at the end (with its Adam state, so --resume continues it), and
    /// --out with .json appended: the validation errors against the mean code's.
    TrainInit(TrainInitOptions),
    /// Inversion accuracy against wall time on held-out objects of a procedural dataset:
    /// input-view and novel-view PSNR/SSIM against the ground truth, for the mean-code
    /// start, the initialiser and each speed option. Writes JSON, a plot and a table.
    Bench(gdrf_core::bench::invert::Options),
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Command::TrainInit(a)) => command::train_init(&a),
        Some(Command::Bench(a)) => gdrf_core::bench::invert::run(&a).map(drop),
        None => command::run(&cli.invert),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
