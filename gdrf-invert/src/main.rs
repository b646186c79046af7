//! gdrf-invert: a photo into shape and appearance features (paper §5), written as the
//! feature file gdrf-edit reads. The commands live in gdrf_core::invert::command and
//! gdrf_core::bench::invert.
use clap::Parser;
use gdrf_core::invert::command::{self, FramingOptions, Options, TrainInitOptions};

/// Invert a photo into GDRF shape and appearance features.
///
/// `gdrf-invert photo.png` finds the object in the photo (its alpha channel, a uniform
/// background on its border, or --mask) and frames it as the generator's training images
/// frame theirs (framing.json beside the generator; see --fit), then starts from what the
/// shipped initialiser reads in it (its shape feature w_s and its camera pose; paper §5.2),
/// renders the generator at that pose and optimises w_s, the appearance modulation
/// (γ_a, β_a) and the pose with Adam on MSE + a perceptual distance + the silhouette's
/// match + priors that keep them near their start (paper §5, and the silhouette term).
/// `--pose` gives the pose instead, `--init none` starts from the mean code, and
/// `--steps 2000` is the paper's schedule (see --steps). Writes into --out:
/// features.safetensors (for `gdrf-edit --shape-from/--appearance-from`), input.png (the
/// photo as compared), reconstruction.png, compare.png (photo | start | result), an orbit of
/// novel views (orbit/frame-NNN.png and orbit.gif), loss.png and invert.json (settings,
/// where the start and the pose came from, timings and the loss of every step).
///
/// `gdrf-invert train-init` trains the initialiser for a generator; `gdrf-invert bench`
/// measures inversion on held-out objects; `gdrf-invert framing` measures where a
/// dataset's objects sit.
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
    /// Train the initialiser F (paper §5.2: ResNet-34 from scratch, or a frozen
    /// ImageNet-pretrained EfficientNet-Lite0 with a trained head) on images the generator
    /// renders, and on a dataset's training-split images at their poses: it predicts w_s,
    /// the camera pose (and optionally the appearance) of a photo. Writes --out atomically
    /// at every validation and at the end (with its Adam state, so --resume continues it),
    /// --out with .json (every validation: held-out errors against the mean code's) and .png
    /// (the curve) appended, and with --ship the half-precision file gdrf-invert and
    /// gdrf-edit use by default.
    TrainInit(TrainInitOptions),
    /// Inversion of held-out objects of a procedural dataset, scored at novel views against
    /// their ground truth (PSNR, a perceptual distance, silhouette IoU, the probe's
    /// structure agreement, pose error) and against time: the mean code, the initialiser,
    /// gdrf-invert's defaults and the paper's 2 000 steps. Writes JSON, a table, a plot and
    /// a figure.
    Bench(gdrf_core::bench::invert::Options),
    /// Measure where the objects sit in a dataset's training images (the range of their
    /// boxes' sizes and centres) and write it beside the generator as framing.json, which
    /// `gdrf-invert PHOTO` uses to frame a photo's object as the generator saw its objects.
    Framing(FramingOptions),
}

fn main() {
    let cli = Cli::parse();
    gdrf_core::progress::set_quiet(cli.invert.quiet);
    let result = match cli.command {
        Some(Command::TrainInit(a)) => command::train_init(&a),
        Some(Command::Bench(a)) => gdrf_core::bench::invert::run(&a).map(drop),
        Some(Command::Framing(a)) => command::framing(&a),
        None => command::run(&cli.invert),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod quiet_tests {
    use super::Cli;
    use clap::CommandFactory;

    #[test]
    fn every_subcommand_takes_quiet() {
        assert_eq!(gdrf_core::progress::without_quiet(&mut Cli::command()), Vec::<String>::new());
    }
}
