//! The c10d bridge across real processes on loopback (Gloo): every entry point between two
//! ranks, and its failures: a port in use, a peer that never arrives, a peer that dies.
//! Each test starts this test binary again as the workers (`GDRF_DIST_WORKER` names the
//! worker to run) and bounds them in time.
mod common;

use common::finish;
use gdrf_core::dist::{Launch, ProcessGroup, Reduce};
use std::process::Child;
use std::time::{Duration, Instant};
use tch::{Device, Kind, Tensor};

const WORKER: &str = "GDRF_DIST_WORKER";

/// One group at a time in this process: a free port picked for one test's rendezvous could
/// otherwise be taken by another test's Gloo connections before its store binds it.
static ONE_GROUP_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// A free port on loopback (bound, then released).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn launch(rank: usize, world: usize, port: u16) -> Launch {
    Launch { rank, world, local_rank: rank, master_addr: "127.0.0.1".into(), master_port: port }
}

/// Starts test `test` of this binary as rank `rank` of `world`, running worker `worker`.
fn spawn(test: &str, worker: &str, rank: usize, world: usize, port: u16) -> Child {
    common::spawn_rank(test, (WORKER, worker.as_ref()), rank, world, port)
}

/// This process's worker, when it was started as one.
fn worker() -> Option<(String, ProcessGroup)> {
    let name = std::env::var(WORKER).ok()?;
    let pg = ProcessGroup::join(&Launch::from_env().unwrap(), Duration::from_secs(20)).unwrap();
    Some((name, pg))
}

/// Rank r's tensors: mixed shapes and dtypes, each filled from r.
fn tensors_of(rank: usize) -> Vec<Tensor> {
    let r = rank as f64 + 1.0;
    vec![
        Tensor::arange(6, (Kind::Float, Device::Cpu)).view([2, 3]) * r,
        Tensor::from_slice(&[r]).to_kind(Kind::Float),
        Tensor::arange(5, (Kind::Double, Device::Cpu)) * r + 0.5,
        Tensor::ones([4, 1, 2], (Kind::Float, Device::Cpu)) * (10.0 * r),
    ]
}

#[test]
fn two_ranks_sum_average_broadcast_and_meet() {
    let _one = one_at_a_time();
    if let Some((_, pg)) = worker() {
        assert_eq!(pg.world(), 2);
        // Buckets of 16 bytes split the list into many collectives; of 1 MiB, one per dtype.
        for bucket_bytes in [16, 1 << 20] {
            let mine = tensors_of(pg.rank());
            pg.all_reduce(&mine, Reduce::Sum, bucket_bytes).unwrap();
            for ((got, a), b) in mine.iter().zip(tensors_of(0)).zip(tensors_of(1)) {
                assert!(got.equal(&(a + b)), "sum, bucket {bucket_bytes}: {got}");
            }
            let mine = tensors_of(pg.rank());
            pg.all_reduce(&mine, Reduce::Average, bucket_bytes).unwrap();
            for ((got, a), b) in mine.iter().zip(tensors_of(0)).zip(tensors_of(1)) {
                assert!(got.allclose(&((a + b) / 2.0), 0.0, 0.0, false), "average, bucket {bucket_bytes}: {got}");
            }
            let mine = tensors_of(pg.rank());
            pg.broadcast(&mine, 1, bucket_bytes).unwrap();
            for (got, want) in mine.iter().zip(tensors_of(1)) {
                assert!(got.equal(&want), "broadcast, bucket {bucket_bytes}: {got}");
            }
        }
        pg.barrier().unwrap();
        println!("rank {} done", pg.rank());
        return;
    }
    let port = free_port();
    let ranks: Vec<Child> =
        (0..2).map(|r| spawn("two_ranks_sum_average_broadcast_and_meet", "collectives", r, 2, port)).collect();
    for (r, child) in ranks.into_iter().enumerate() {
        let (ok, said) = finish(child, Duration::from_secs(60), &format!("rank {r}"));
        assert!(ok && said.contains(&format!("rank {r} done")), "rank {r}:\n{said}");
    }
}

#[test]
fn a_port_in_use_is_an_error_naming_master_port() {
    let _one = one_at_a_time();
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let start = Instant::now();
    let e = ProcessGroup::join(&launch(0, 1, port), Duration::from_secs(5)).unwrap_err().to_string();
    assert!(e.contains("MASTER_PORT") && e.contains(&port.to_string()) && e.contains("rank 0 of 1"), "{e}");
    assert!(start.elapsed() < Duration::from_secs(30), "took {:?}", start.elapsed());
    println!("{e}");
}

#[test]
fn a_peer_that_never_arrives_is_an_error_within_the_timeout() {
    let _one = one_at_a_time();
    let start = Instant::now();
    let e = ProcessGroup::join(&launch(0, 2, free_port()), Duration::from_secs(3)).unwrap_err().to_string();
    let took = start.elapsed();
    assert!(e.contains("rank 0 of 2") && e.contains("could not join"), "{e}");
    assert!(took >= Duration::from_secs(2) && took < Duration::from_secs(30), "took {took:?}: {e}");
    println!("after {took:?}: {e}");
}

#[test]
fn a_peer_that_dies_makes_the_other_rank_fail_not_hang() {
    let _one = one_at_a_time();
    if let Some((_, pg)) = worker() {
        pg.barrier().unwrap();
        if pg.rank() == 1 {
            // Dies without leaving the group, as a killed process does.
            std::process::abort();
        }
        std::thread::sleep(Duration::from_millis(500));
        let t = [Tensor::ones([8], (Kind::Float, Device::Cpu))];
        let e = pg.all_reduce(&t, Reduce::Sum, 1 << 20).unwrap_err().to_string();
        println!("rank 0 failed as it should: {e}");
        return;
    }
    let port = free_port();
    let ranks: Vec<Child> =
        (0..2).map(|r| spawn("a_peer_that_dies_makes_the_other_rank_fail_not_hang", "dies", r, 2, port)).collect();
    let mut ranks = ranks.into_iter();
    let (zero, one) = (ranks.next().unwrap(), ranks.next().unwrap());
    let start = Instant::now();
    let (ok, said) = finish(zero, Duration::from_secs(60), "rank 0");
    assert!(ok && said.contains("rank 0 failed as it should") && said.contains("all-reduce on rank 0 of 2"), "{said}");
    println!("rank 0 after {:?}: {said}", start.elapsed());
    let (ok, _) = finish(one, Duration::from_secs(10), "rank 1");
    assert!(!ok, "rank 1 was meant to die");
}

/// The NCCL group for CUDA tensors, asked for where CUDA is missing (this machine, or a
/// build without NCCL): an error that says so, not an abort; the Gloo group still works.
#[test]
fn an_nccl_group_without_cuda_is_an_error_not_an_abort() {
    if tch::Cuda::is_available() {
        println!("CUDA is present: this test is about its absence");
        return;
    }
    let _one = one_at_a_time();
    let pg = ProcessGroup::join(&launch(0, 1, free_port()), Duration::from_secs(10)).unwrap();
    let e = pg.use_nccl_for_cuda().unwrap_err().to_string();
    assert!(e.contains("rank 0 of 1 could not make its NCCL group"), "{e}");
    println!("{e}");
    let t = [Tensor::from_slice(&[1.0f32, 2.0])];
    pg.all_reduce(&t, Reduce::Sum, 64).unwrap();
    assert_eq!(Vec::<f32>::try_from(&t[0]).unwrap(), [1.0, 2.0]);
}
