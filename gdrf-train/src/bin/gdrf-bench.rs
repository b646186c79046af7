//! gdrf-bench: benchmarks run side by side with the PyTorch reference (scripts/reference/),
//! printing medians and ratios and writing JSON and a bar chart.
use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use gdrf_core::camera::Poses;
use gdrf_core::disc::Discriminator;
use gdrf_core::loss::{discriminator_loss, generator_loss, FakeBatch, LossConfig, Schedule};
use gdrf_core::render::{Noise, Renderer};
use gdrf_core::{device, CameraConfig, Generator, GeneratorConfig, RenderConfig};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;
use tch::{nn, Kind, Tensor};

#[derive(Parser)]
#[command(version, about = "Benchmarks of gdrf against the PyTorch reference, in one run.")]
struct Cli {
    #[command(subcommand)]
    command: Bench,
}

#[derive(Subcommand)]
enum Bench {
    /// One generator loss + backward and one discriminator loss + backward (release
    /// settings: regularisers on, R1 every step). The batch is processed in
    /// `--batch-split` chunks for G, as the release does, so that one 64² image's graph
    /// (about 12 GB in float32) fits in memory.
    Losses {
        #[arg(long, default_value_t = 4)]
        batch: i64,
        #[arg(long, default_value_t = 4)]
        batch_split: i64,
        #[arg(long, default_value_t = 64)]
        resolution: i64,
        /// Coarse samples per ray (the importance pass adds as many).
        #[arg(long, default_value_t = 36)]
        steps: usize,
        /// Timed repetitions per implementation (medians are reported).
        #[arg(long, default_value_t = 1)]
        repeats: usize,
        /// Skip the PyTorch reference (report gdrf alone).
        #[arg(long)]
        no_reference: bool,
        /// Folder for losses.json and losses.png.
        #[arg(long, default_value = "bench")]
        out_dir: PathBuf,
    },
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).map(|l| l.to_string()))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<f64>().ok()))
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

fn python() -> PathBuf {
    std::env::var_os("GDRF_PYTHON").map(PathBuf::from).unwrap_or_else(|| root().join(".venv/bin/python"))
}

#[allow(clippy::too_many_arguments)]
fn bench_losses(b: i64, split: i64, res: i64, steps: usize, repeats: usize) -> Result<serde_json::Value> {
    let threads = device::init_threads();
    tch::manual_seed(0);
    let gvs = nn::VarStore::new(tch::Device::Cpu);
    let gen = Generator::new(&gvs.root(), &GeneratorConfig::default())?;
    let dvs = nn::VarStore::new(tch::Device::Cpu);
    let disc = Discriminator::new(&dvs.root());
    let camera = CameraConfig::chair();
    let config = RenderConfig { num_steps: steps, ..Default::default() };
    let renderer = Renderer::new(&gen, &camera, &config)?;
    let cfg = LossConfig::default();
    let at = Schedule { step: 0, alpha: 1.0 };
    let chunk = b / split;
    let latent = gen.cfg.latent_dim as i64;
    let mut t: std::collections::BTreeMap<&str, Vec<f64>> = Default::default();
    let zero = |vs: &nn::VarStore| {
        for (_, mut v) in vs.variables() {
            if v.grad().defined() {
                v.zero_grad();
            }
        }
    };
    for _ in 0..repeats {
        zero(&gvs);
        zero(&dvs);
        let (mut fwd, mut bwd) = (0.0, 0.0);
        for _ in 0..split {
            let t0 = Instant::now();
            let z = Tensor::randn([chunk, latent], (Kind::Float, tch::Device::Cpu));
            let poses = Poses::sample(&camera, chunk, Kind::Float, tch::Device::Cpu);
            let lat = gen.latents(&z, &z, None);
            let noise = Noise::default();
            let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
            let loss = generator_loss(&renderer, &disc, &fake, at, &cfg, None)?;
            let t1 = Instant::now();
            loss.total.backward();
            fwd += (t1 - t0).as_secs_f64();
            bwd += t1.elapsed().as_secs_f64();
        }
        t.entry("g_forward").or_default().push(fwd);
        t.entry("g_backward").or_default().push(bwd);

        zero(&dvs);
        let t0 = Instant::now();
        let z = Tensor::randn([b, latent], (Kind::Float, tch::Device::Cpu));
        let poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu);
        let lat = tch::no_grad(|| gen.latents(&z, &z, None));
        let noise = Noise::default();
        let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
        let real = Tensor::rand([b, 3, res, res], (Kind::Float, tch::Device::Cpu)) * 2.0 - 1.0;
        let real_poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu).stacked();
        let loss = discriminator_loss(&renderer, &disc, &real, &real_poses, &fake, at, &cfg)?;
        let t1 = Instant::now();
        loss.total.backward();
        t.entry("d_forward").or_default().push((t1 - t0).as_secs_f64());
        t.entry("d_backward").or_default().push(t1.elapsed().as_secs_f64());
    }
    let med: serde_json::Map<String, serde_json::Value> = t.iter().map(|(k, v)| (k.to_string(), json!(median(v)))).collect();
    Ok(json!({
        "implementation": "gdrf (tch)",
        "threads": threads,
        "median_s": med,
        "samples_s": t,
        "peak_rss_mb": peak_rss_mb(),
    }))
}

fn run() -> Result<()> {
    match Cli::parse().command {
        Bench::Losses { batch, batch_split, resolution, steps, repeats, no_reference, out_dir } => {
            if batch_split < 1 || batch % batch_split != 0 {
                bail!("--batch-split {batch_split} must divide --batch {batch}");
            }
            if repeats == 0 {
                bail!("--repeats must be at least 1");
            }
            let title = format!(
                "G and D loss + backward, batch {batch} (split {batch_split}), {resolution}², {steps}+{steps} samples, regularisers on"
            );
            eprintln!("{title}\nrunning gdrf (after an untimed warm-up at 16²) …");
            bench_losses(batch_split, batch_split, 16, 8, 1)?;
            let mut runs = vec![bench_losses(batch, batch_split, resolution, steps, repeats)?];
            if !no_reference {
                eprintln!("running the PyTorch reference …");
                let out = Command::new(python())
                    .arg(root().join("scripts/reference/bench_losses.py"))
                    .args(["--batch", &batch.to_string(), "--batch-split", &batch_split.to_string()])
                    .args(["--resolution", &resolution.to_string(), "--steps", &steps.to_string()])
                    .args(["--repeats", &repeats.to_string()])
                    .output()
                    .context("starting the PyTorch reference (run scripts/setup.sh)")?;
                if !out.status.success() {
                    bail!("the PyTorch reference failed:\n{}", String::from_utf8_lossy(&out.stderr));
                }
                runs.push(serde_json::from_slice(&out.stdout).context("reading the reference's JSON")?);
            }
            println!("{title}");
            println!("{:<14}{:>14}{:>14}{:>14}{:>14}{:>12}", "", "G forward s", "G backward s", "D forward s", "D backward s", "peak MB");
            let phases = ["g_forward", "g_backward", "d_forward", "d_backward"];
            for r in &runs {
                print!("{:<14}", r["implementation"].as_str().unwrap_or("?"));
                for p in phases {
                    print!("{:>14.2}", r["median_s"][p].as_f64().unwrap_or(f64::NAN));
                }
                println!("{:>12.0}", r["peak_rss_mb"].as_f64().unwrap_or(f64::NAN));
            }
            if runs.len() == 2 {
                let total = |r: &serde_json::Value, a: &str, b: &str| {
                    r["median_s"][a].as_f64().unwrap() + r["median_s"][b].as_f64().unwrap()
                };
                for (name, a, b) in [("G loss + backward", "g_forward", "g_backward"), ("D loss + backward", "d_forward", "d_backward")] {
                    let (x, y) = (total(&runs[0], a, b), total(&runs[1], a, b));
                    println!("{name}: gdrf {x:.2} s, reference {y:.2} s, reference/gdrf = {:.2}×", y / x);
                }
            }
            std::fs::create_dir_all(&out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
            let json_path = out_dir.join("losses.json");
            let doc = json!({"title": title, "machine": format!("{} CPU threads", runs[0]["threads"]), "phases": phases, "runs": runs});
            gdrf_core::checkpoint::write_atomic(&json_path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
            let png = out_dir.join("losses.png");
            let status = Command::new(python())
                .arg(root().join("scripts/plot_bench.py"))
                .args([&json_path, &png])
                .status()
                .context("starting scripts/plot_bench.py")?;
            if !status.success() {
                bail!("plotting failed (is matplotlib installed? run scripts/setup.sh)");
            }
            println!("wrote {} and {}", json_path.display(), png.display());
        }
    }
    Ok(())
}
