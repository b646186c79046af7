//! gdrf-bench: benchmarks run side by side with the PyTorch reference (scripts/reference/),
//! printing medians and ratios and writing JSON and a bar chart (gdrf_core::bench).
use clap::{Parser, Subcommand};
use gdrf_core::bench::{allreduce, losses, shared_grid, step, step_summary};

#[derive(Parser)]
#[command(version, about = "Benchmarks of gdrf against the PyTorch reference, in one run.")]
struct Cli {
    #[command(subcommand)]
    command: Bench,
    /// No progress bars (`gdrf-bench step --quiet`), as in the other binaries.
    #[arg(long, global = true)]
    quiet: bool,
}

#[derive(Subcommand)]
enum Bench {
    /// One generator loss + backward and one discriminator loss + backward (release
    /// settings: regularisers on, R1 every step). The batch is processed in
    /// `--batch-split` chunks for G, as the release does, so that one 64² image's graph
    /// (about 12 GB in float32) fits in memory.
    Losses(losses::Options),
    /// Full training steps (D step, G step, clipping, Adam, EMA) of a training config's
    /// stage, gdrf's `Trainer::step` against the PyTorch reference at the same sizes, on
    /// the CPU or a GPU (`--device`), in float32 or bfloat16. Real images come from a small procedural dataset generated in a temporary
    /// folder (the reference uses random images). Timed steps are steps where R1 is due.
    /// On a CPU in float32, gdrf also runs with libtorch's sine (MKL) in place of its own
    /// (SLEEF). `--nproc N`: data-parallel scaling, N ranks of one thread against one
    /// process of N.
    Step(step::Options),
    /// Several `step` outputs side by side (e.g. the full-image step at 32², 64² and 128²
    /// and the scaled-patch step): a table, STEM.json and a bar chart STEM.png.
    StepSummary(step_summary::Options),
    /// The gradient all-reduce of data-parallel training (a config's generator and
    /// discriminator parameters, Gloo over loopback, one thread a rank) against the bucket
    /// size, through gdrf's c10d bridge and through torch.distributed.
    Allreduce(allreduce::Options),
    /// What a training-time occupancy grid shared by all shape codes (nerfacc's grid, the
    /// maximum over codes) would let a step skip: the union of 1, 2, 4, … codes' own grids
    /// at each density threshold, walked by training rays; the share of rays that meet it
    /// and of the ray interval it keeps (one code's own grid beside it). No timing.
    SharedGrid(shared_grid::Options),
}

fn main() {
    let cli = Cli::parse();
    gdrf_core::progress::set_quiet(cli.quiet);
    let result = match cli.command {
        Bench::Losses(a) => losses::run(&a).map(drop),
        Bench::Step(a) => step::run(&a).map(drop),
        Bench::StepSummary(a) => step_summary::run(&a).map(drop),
        Bench::Allreduce(a) => allreduce::run(&a).map(drop),
        Bench::SharedGrid(a) => shared_grid::run(&a).map(drop),
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
