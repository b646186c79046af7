//! Data-parallel training against one process: 2 ranks × batch 4 (each a process of this
//! test binary, joined through the c10d bridge over loopback) reach the same generator,
//! EMA and discriminator weights after a few steps as 1 process × batch 8, within float32
//! tolerance, and the two ranks stay identical replicas.
mod common;

use common::TempDir;
use gdrf_core::dist::{Launch, ProcessGroup};
use gdrf_core::train::{TrainConfig, Trainer};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tch::Tensor;

const STEPS: usize = 3;

fn config(dir: &Path) -> PathBuf {
    let text = common::tiny_training_toml(
        "seed = 3\nthreads = 1",
        "total_steps = 100\nlog_interval = 1\ncheckpoint_interval = 1000\nsample_interval = 0",
        r#"
[[stages]]
from_step = 0
resolution = 8
num_steps = 4
batch_size = 8

[data]
path = "data"

[data.synth]
count = 16
resolution = 16
supersample = 1
shadows = false
"#,
    );
    let path = dir.join("parallel.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// Every weight of the trainer's three networks, by network-prefixed name.
fn weights(t: &Trainer) -> Vec<(String, Tensor)> {
    let mut out = Vec::new();
    for (prefix, vs) in [("generator.", t.generator_vars()), ("ema.", t.ema_vars()), ("discriminator.", t.disc_vars())] {
        for (name, v) in vs.variables() {
            out.push((format!("{prefix}{name}"), v.detach().copy()));
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

/// `STEPS` steps of the config in `dir` with run folder `run`, as a rank of `group` or alone.
fn train(dir: &Path, run: &str, group: Option<ProcessGroup>) -> Trainer {
    let cfg = TrainConfig::load(&config(dir)).unwrap();
    let mut t = Trainer::new(cfg, &dir.join(run)).unwrap();
    t.set_threads(1);
    t.prepare_data(&|| {}).unwrap();
    if let Some(g) = group {
        t.join_group(g).unwrap();
    }
    for _ in 0..STEPS {
        let r = t.step().unwrap();
        println!("step {}: d {:.6} g {:.6}", r.step, r.d_total, r.g_total);
    }
    t
}

#[test]
fn two_ranks_of_batch_4_train_as_one_process_of_batch_8() {
    if let Ok(dir) = std::env::var("GDRF_DIST_TRAIN_DIR") {
        let dir = PathBuf::from(dir);
        let launch = Launch::from_env().unwrap();
        let group = ProcessGroup::join(&launch, Duration::from_secs(60)).unwrap();
        let t = train(&dir, &format!("rank-{}", launch.rank), Some(group));
        assert_eq!(t.shard(8), (4 * launch.rank as i64, 4), "rank {}'s rows of the batch", launch.rank);
        Tensor::write_safetensors(&weights(&t), dir.join(format!("rank-{}.safetensors", launch.rank))).unwrap();
        return;
    }
    let dir = TempDir::new("dist-train").unwrap();
    // One process first: it also makes the dataset the ranks then read.
    let alone = weights(&train(&dir.0, "alone", None));
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let ranks: Vec<_> = (0..2)
        .map(|rank| {
            Command::new(std::env::current_exe().unwrap())
                .args(["--exact", "two_ranks_of_batch_4_train_as_one_process_of_batch_8", "--nocapture"])
                .env("GDRF_DIST_TRAIN_DIR", &dir.0)
                .env("RANK", rank.to_string())
                .env("WORLD_SIZE", "2")
                .env("MASTER_ADDR", "127.0.0.1")
                .env("MASTER_PORT", port.to_string())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for (rank, mut child) in ranks.into_iter().enumerate() {
        let start = Instant::now();
        while child.try_wait().unwrap().is_none() {
            if start.elapsed() > Duration::from_secs(300) {
                let _ = child.kill();
                panic!("rank {rank} still running after 5 minutes");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let out = child.wait_with_output().unwrap();
        let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "rank {rank}:\n{said}");
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
