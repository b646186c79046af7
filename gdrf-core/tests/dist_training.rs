//! Data-parallel training against one process: 2 ranks × batch 4 (each a process of this
//! test binary, joined through the c10d bridge over loopback) reach the same generator,
//! EMA and discriminator weights and Adam moments (every tensor of a checkpoint) after a
//! few steps as 1 process × batch 8, within float32 tolerance, and the two ranks stay
//! identical replicas. Three settings: each rank judging its own rows (the release's step,
//! with the coverage term), and every rank judging the global batch (a minibatch-std
//! discriminator, augmentation, mode-seeking pairs and a top-k that drops images from step
//! 1 on), with the release's step in bands and with the one-render step.
mod common;

use common::TempDir;
use gdrf_core::dist::{Launch, ProcessGroup};
use gdrf_core::train::{TrainConfig, Trainer};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tch::Tensor;

const STEPS: usize = 3;

/// The config of each setting (`variant`), written into `dir`.
fn config(dir: &Path, variant: &str) -> PathBuf {
    let (top, stage, across) = match variant {
        "own" => ("", "", false),
        "global" => ("", "regions = 2", true),
        "global-one-render" => ("step = \"one-render\"", "", true),
        _ => panic!("no setting {variant}"),
    };
    // Top-k keeps ceil(0.99^(step / 0.05)·8) of 8 fakes: 7 at step 1, 6 at step 2 (of 4
    // per rank: 4 and 3, were each rank to pick its own).
    let loss = if across {
        "[loss]\ndiversity_weight = 50.0\ntopk_interval = 0.05"
    } else {
        // The coverage term: per real image, its nearest of 4 candidate codes.
        "[loss]\ncoverage_weight = 1.0\ncoverage_candidates = 4"
    };
    let text = common::tiny_training_toml(
        &format!("seed = 3\nthreads = 1\n{top}"),
        "total_steps = 100\nlog_interval = 1\ncheckpoint_interval = 1000\nsample_interval = 0",
        &format!(
            r#"
[[stages]]
from_step = 0
resolution = 8
num_steps = 4
batch_size = 8
{stage}

[data]
path = "data"

[data.synth]
count = 16
resolution = 16
supersample = 1
shadows = false

{loss}
"#
        ),
    );
    let text = if across {
        text.replace(
            "[discriminator]\n",
            "[discriminator]\nminibatch_std_group = 4\naugment = [\"color\", \"translation\", \"cutout\"]\n",
        )
    } else {
        text
    };
    // Each rank writes it too: by rename, so that none reads another's half-written file.
    let path = dir.join(format!("{variant}.toml"));
    let tmp = dir.join(format!("{variant}.toml.{}", std::process::id()));
    std::fs::write(&tmp, text).unwrap();
    std::fs::rename(&tmp, &path).unwrap();
    path
}

/// Every tensor of a checkpoint of the trainer: the three networks' weights and both
/// optimisers' moments, by name.
fn state(t: &Trainer) -> Vec<(String, Tensor)> {
    let path = t.save_checkpoint().unwrap();
    let mut out = Tensor::read_safetensors(&path).unwrap();
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

/// `STEPS` steps of setting `variant` in `dir` with run folder `run`, as a rank of `group` or alone.
fn train(dir: &Path, variant: &str, run: &str, group: Option<ProcessGroup>) -> Trainer {
    let cfg = TrainConfig::load(&config(dir, variant)).unwrap();
    let mut t = Trainer::new(cfg, &dir.join(run)).unwrap();
    t.set_threads(1);
    t.prepare_data(&|_| {}).unwrap();
    if let Some(g) = group {
        t.join_group(g).unwrap();
    }
    for _ in 0..STEPS {
        let r = t.step().unwrap();
        println!("step {}: d {:.6} g {:.6}", r.step, r.d_total, r.g_total);
    }
    t
}

/// Runs setting `variant` in one process and in two ranks (this test binary again, as test
/// `test`), and compares the weights.
fn two_ranks_train_as_one_process(variant: &str, test: &str) {
    if let Ok(dir) = std::env::var("GDRF_DIST_TRAIN_DIR") {
        let dir = PathBuf::from(dir);
        let launch = Launch::from_env().unwrap();
        let group = ProcessGroup::join(&launch, Duration::from_secs(60)).unwrap();
        let t = train(&dir, variant, &format!("rank-{}", launch.rank), Some(group));
        assert_eq!(t.shard(8), (4 * launch.rank as i64, 4), "rank {}'s rows of the batch", launch.rank);
        Tensor::write_safetensors(&state(&t), dir.join(format!("rank-{}.safetensors", launch.rank))).unwrap();
        return;
    }
    let dir = TempDir::new("dist-train").unwrap();
    // One process first: it also makes the dataset the ranks then read.
    let alone = state(&train(&dir.0, variant, "alone", None));
    let moments = alone.iter().filter(|(n, _)| n.contains("adam")).count();
    assert!(moments > 0, "no optimiser moments among {:?}", alone.iter().map(|(n, _)| n).collect::<Vec<_>>());
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let ranks: Vec<_> = (0..2)
        .map(|rank| common::spawn_rank(test, ("GDRF_DIST_TRAIN_DIR", dir.0.as_os_str()), rank, 2, port))
        .collect();
    for (rank, child) in ranks.into_iter().enumerate() {
        let (ok, said) = common::finish(child, Duration::from_secs(300), &format!("rank {rank}"));
        assert!(ok, "rank {rank}:\n{said}");
        println!("rank {rank}:\n{said}");
    }
    let read = |r: usize| -> HashMap<String, Tensor> {
        Tensor::read_safetensors(dir.path(&format!("rank-{r}.safetensors"))).unwrap().into_iter().collect()
    };
    let (zero, one) = (read(0), read(1));
    assert_eq!(zero.len(), alone.len());
    let mut worst = 0.0f64;
    let mut bitwise = 0;
    for (name, want) in &alone {
        assert!(zero[name].equal(&one[name]), "{name}: the ranks' replicas differ");
        let r = common::assert_close(name, &zero[name], want, 2e-5, 1e-4);
        worst = worst.max(r);
        bitwise += usize::from(zero[name].equal(want));
    }
    println!("{} tensors ({bitwise} bitwise equal); worst |Δ| / (atol + rtol·|w|) = {worst:.4}", alone.len());
    // Each rank's half of the batch sums in another order than the whole batch does: were
    // every weight bitwise equal, the ranks would have trained on the whole batch each.
    assert!(bitwise < alone.len(), "every weight bitwise equal to one process's: the batch was not split");
}

// The tests spawn processes that join a group on a port of their own; one at a time keeps
// the two cores from timing each other's ranks out.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn two_ranks_of_batch_4_train_as_one_process_of_batch_8() {
    let _one = ONE_AT_A_TIME.lock();
    two_ranks_train_as_one_process("own", "two_ranks_of_batch_4_train_as_one_process_of_batch_8");
}

#[test]
fn two_ranks_judging_the_global_batch_train_as_one_process() {
    let _one = ONE_AT_A_TIME.lock();
    two_ranks_train_as_one_process("global", "two_ranks_judging_the_global_batch_train_as_one_process");
}

#[test]
fn two_ranks_judging_the_global_batch_in_one_render_train_as_one_process() {
    let _one = ONE_AT_A_TIME.lock();
    two_ranks_train_as_one_process(
        "global-one-render",
        "two_ranks_judging_the_global_batch_in_one_render_train_as_one_process",
    );
}
