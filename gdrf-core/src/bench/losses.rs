//! `gdrf-bench losses`: one generator loss + backward and one discriminator loss +
//! backward of gdrf beside the PyTorch reference (scripts/reference/bench_losses.py).
use super::{median, peak_rss_mb, reference_run, Run, Timings};
use crate::camera::Poses;
use crate::disc::Discriminator;
use crate::loss::{LossConfig, Schedule};
use crate::render::{Noise, Renderer};
use crate::train::{discriminator_pass, generator_pass, FakeBatch};
use crate::{device, CameraConfig, Error, Generator, GeneratorConfig, RenderConfig, Result};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;
use tch::{nn, Kind, Tensor};

/// The flags of `gdrf-bench losses`.
#[derive(clap::Args)]
pub struct Options {
    #[arg(long, default_value_t = 4)]
    pub batch: i64,
    #[arg(long, default_value_t = 4)]
    pub batch_split: i64,
    #[arg(long, default_value_t = 64)]
    pub resolution: i64,
    /// Coarse samples per ray (the importance pass adds as many).
    #[arg(long, default_value_t = 36)]
    pub steps: usize,
    /// Timed repetitions per implementation (medians are reported).
    #[arg(long, default_value_t = 1)]
    pub repeats: usize,
    /// Skip the PyTorch reference (report gdrf alone).
    #[arg(long)]
    pub no_reference: bool,
    /// Folder for losses.json and losses.png.
    #[arg(long, default_value = "bench")]
    pub out_dir: PathBuf,
}

/// The phases timed, in the order they are drawn.
const PHASES: [&str; 4] = ["g_forward", "g_backward", "d_forward", "d_backward"];

/// Runs gdrf (after an untimed warm-up at 16²) and the reference, prints the table and
/// writes losses.json and losses.png into `--out-dir`.
pub fn run(a: &Options) -> Result<Timings<()>> {
    let (batch, batch_split, resolution, steps, repeats) = (a.batch, a.batch_split, a.resolution, a.steps, a.repeats);
    if batch_split < 1 || batch % batch_split != 0 {
        return Err(Error::Invalid(format!("--batch-split {batch_split} must divide --batch {batch}")));
    }
    if repeats == 0 {
        return Err(Error::Invalid("--repeats must be at least 1".into()));
    }
    let title = format!(
        "G and D loss + backward, batch {batch} (split {batch_split}), {resolution}², {steps}+{steps} samples, regularisers on"
    );
    eprintln!("{title}\nrunning gdrf (after an untimed warm-up at 16²) …");
    measure(batch_split, batch_split, 16, 8, 1)?;
    let mut runs = vec![measure(batch, batch_split, resolution, steps, repeats)?];
    if !a.no_reference {
        let pairs = [
            ("--batch", batch),
            ("--batch-split", batch_split),
            ("--resolution", resolution),
            ("--steps", steps as i64),
            ("--repeats", repeats as i64),
        ];
        let args: Vec<String> = pairs.iter().flat_map(|(k, v)| [k.to_string(), v.to_string()]).collect();
        runs.push(reference_run("bench_losses.py", &args)?);
    }
    println!("{title}");
    println!(
        "{:<14}{:>14}{:>14}{:>14}{:>14}{:>12}",
        "", "G forward s", "G backward s", "D forward s", "D backward s", "peak MB"
    );
    for r in &runs {
        print!("{:<14}", r.implementation);
        for p in PHASES {
            print!("{:>14.2}", r.median(p));
        }
        println!("{:>12.0}", r.peak_rss_mb);
    }
    if let [x, y] = &runs[..] {
        for (name, fwd, bwd) in
            [("G loss + backward", "g_forward", "g_backward"), ("D loss + backward", "d_forward", "d_backward")]
        {
            let (x, y) = (x.median(fwd) + x.median(bwd), y.median(fwd) + y.median(bwd));
            println!("{name}: gdrf {x:.2} s, reference {y:.2} s, reference/gdrf = {:.2}×", y / x);
        }
    }
    let doc = Timings {
        title,
        machine: format!("{} CPU threads", runs[0].threads),
        settings: None,
        phases: PHASES.to_vec(),
        runs,
    };
    doc.write(&a.out_dir, "losses")?;
    Ok(doc)
}

/// `repeats` timed generator and discriminator passes of batch `b` in `split` chunks for
/// G, at `res`² with `steps` + `steps` samples per ray, on the CPU.
fn measure(b: i64, split: i64, res: i64, steps: usize, repeats: usize) -> Result<Run> {
    let threads = device::init_threads();
    let gvs = nn::VarStore::new(tch::Device::Cpu);
    let gen = crate::rng::with_global_seed(0, || Generator::new(&gvs.root(), &GeneratorConfig::default()))?;
    let mut dvs = nn::VarStore::new(tch::Device::Cpu);
    let disc = Discriminator::new(&dvs.root());
    let camera = CameraConfig::chair();
    let config = RenderConfig { num_steps: steps, ..Default::default() };
    let renderer = Renderer::new(&gen, &camera, &config)?;
    let cfg = LossConfig::default();
    let at = Schedule { step: 0, alpha: 1.0 };
    let chunk = b / split;
    let latent = gen.cfg.latent_dim as i64;
    let mut t: BTreeMap<&str, Vec<f64>> = Default::default();
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
        // The generator step leaves D frozen: no D parameter gradients are computed.
        dvs.freeze();
        let (mut fwd, mut bwd) = (0.0, 0.0);
        for _ in 0..split {
            let t0 = Instant::now();
            let z = Tensor::randn([chunk, latent], (Kind::Float, tch::Device::Cpu));
            let poses = Poses::sample(&camera, chunk, Kind::Float, tch::Device::Cpu);
            let lat = gen.latents(&z, &z, None)?;
            let noise = Noise::default();
            let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
            let loss = generator_pass(&renderer, &disc, &fake, None, at, &cfg)?;
            let t1 = Instant::now();
            loss.total.backward();
            fwd += (t1 - t0).as_secs_f64();
            bwd += t1.elapsed().as_secs_f64();
        }
        t.entry("g_forward").or_default().push(fwd);
        t.entry("g_backward").or_default().push(bwd);
        dvs.unfreeze();

        zero(&dvs);
        let t0 = Instant::now();
        let z = Tensor::randn([b, latent], (Kind::Float, tch::Device::Cpu));
        let poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu);
        let lat = tch::no_grad(|| gen.latents(&z, &z, None))?;
        let noise = Noise::default();
        let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
        let real = Tensor::rand([b, 3, res, res], (Kind::Float, tch::Device::Cpu)) * 2.0 - 1.0;
        let real_poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu).stacked();
        let loss = discriminator_pass(&renderer, &disc, &real, Some(&real_poses), &fake, at, &cfg)?;
        let t1 = Instant::now();
        loss.total.backward();
        t.entry("d_forward").or_default().push((t1 - t0).as_secs_f64());
        t.entry("d_backward").or_default().push(t1.elapsed().as_secs_f64());
    }
    Ok(Run {
        implementation: "gdrf (tch)".into(),
        threads,
        median_s: t.iter().map(|(k, v)| (k.to_string(), median(v))).collect(),
        samples_s: t.into_iter().map(|(k, v)| (k.to_string(), v)).collect(),
        peak_rss_mb: peak_rss_mb(),
        images_per_second: None,
        other: Default::default(),
    })
}
