//! The process group of data-parallel training: libtorch's own c10d with the Gloo backend
//! (the engine PyTorch's DistributedDataParallel uses), reached through the narrow C shim
//! in `c10d.cpp`, the only code of the project that knows about C++.
//!
//! - [`Launch`]: where a worker stands (rank, world size, local rank, the rendezvous
//!   address), from the variables torchrun sets (`RANK`, `WORLD_SIZE`, `LOCAL_RANK`,
//!   `MASTER_ADDR`, `MASTER_PORT`). A missing or wrong one is an error naming it.
//! - [`ProcessGroup`]: joined through a TCPStore that rank 0 serves; all-reduce (sum or
//!   average) of a list of tensors flattened into buckets, broadcast from one rank, barrier.
//!   A peer that dies or never comes, or a collective past the timeout, is an error, never
//!   an abort or a hang.
//!
//! The shim compiles against the wheel's c10d headers and gloo's (third_party/gloo).
use crate::{Error, Result};
use std::time::Duration;
use tch::Tensor;

/// torchrun's port when none is given.
pub const DEFAULT_PORT: u16 = 29500;

/// One worker's place in a data-parallel run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Launch {
    /// 0 ≤ rank < world.
    pub rank: usize,
    pub world: usize,
    /// The rank among the workers of this machine: its GPU (`cuda:LOCAL_RANK`).
    pub local_rank: usize,
    /// Where rank 0 serves the rendezvous store.
    pub master_addr: String,
    pub master_port: u16,
}

impl Launch {
    /// From the process's environment (torchrun's variables).
    pub fn from_env() -> Result<Self> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// From `var` (a variable's value by name). `LOCAL_RANK` defaults to `RANK`, and
    /// `MASTER_PORT` to 29500, as with torchrun; the rest must be set.
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<Self> {
        let number = |name: &str, default: Option<usize>| -> Result<usize> {
            match var(name) {
                Some(v) => v
                    .trim()
                    .parse::<usize>()
                    .map_err(|_| Error::Distributed(format!("{name} is '{v}', expected a whole number ≥ 0"))),
                None => default.ok_or_else(|| {
                    Error::Distributed(format!("{name} is not set (torchrun and `gdrf-train --nproc` set it)"))
                }),
            }
        };
        let world = number("WORLD_SIZE", None)?;
        if world == 0 {
            return Err(Error::Distributed("WORLD_SIZE is 0, expected at least 1".into()));
        }
        let rank = number("RANK", None)?;
        if rank >= world {
            return Err(Error::Distributed(format!("RANK is {rank}, expected less than WORLD_SIZE ({world})")));
        }
        let local_rank = number("LOCAL_RANK", Some(rank))?;
        let master_addr = var("MASTER_ADDR")
            .filter(|a| !a.trim().is_empty())
            .ok_or_else(|| Error::Distributed("MASTER_ADDR is not set (the address of rank 0's machine)".into()))?;
        let port = number("MASTER_PORT", Some(DEFAULT_PORT as usize))?;
        let master_port = u16::try_from(port)
            .ok()
            .filter(|&p| p > 0)
            .ok_or_else(|| Error::Distributed(format!("MASTER_PORT is {port}, expected 1 to 65535")))?;
        Ok(Self { rank, world, local_rank, master_addr: master_addr.trim().to_string(), master_port })
    }
}

/// How [`ProcessGroup::all_reduce`] combines the ranks' tensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reduce {
    Sum,
    /// The sum divided by the world size (floating-point tensors only).
    Average,
}

/// A joined c10d process group: Gloo, and NCCL for CUDA tensors once
/// [`ProcessGroup::use_nccl_for_cuda`] asked for it. Dropping it leaves the group.
#[derive(Debug)]
pub struct ProcessGroup {
    raw: ffi::Raw,
    rank: usize,
    world: usize,
    timeout: Duration,
    /// Seconds spent in collectives so far (waiting for slower ranks included).
    busy: std::cell::Cell<f64>,
}

// The c10d process group may be used from any one thread at a time.
unsafe impl Send for ProcessGroup {}

impl ProcessGroup {
    /// Joins the group of `launch` (every rank must call it; rank 0 serves the store).
    /// `timeout` bounds the rendezvous and every later collective: a peer that never
    /// arrives or stops answering makes this rank's call an error after it.
    pub fn join(launch: &Launch, timeout: Duration) -> Result<Self> {
        let loopback = launch.master_addr == "localhost" || launch.master_addr.starts_with("127.");
        // On one machine the group binds to loopback; across machines to this machine's
        // own hostname, as torch's default device does.
        let bind = if loopback { "127.0.0.1" } else { "" };
        let raw = ffi::new(launch, bind, timeout).map_err(|why| {
            Error::Distributed(format!(
                "rank {} of {} could not join the group at MASTER_ADDR:MASTER_PORT {}:{} within {:.0?}: {why}",
                launch.rank, launch.world, launch.master_addr, launch.master_port, timeout
            ))
        })?;
        Ok(Self { raw, rank: launch.rank, world: launch.world, timeout, busy: Default::default() })
    }

    pub fn rank(&self) -> usize {
        self.rank
    }

    pub fn world(&self) -> usize {
        self.world
    }

    /// Seconds this process has spent in the group's collectives (the step benchmark's
    /// all-reduce share); a collective's wait for slower ranks counts too.
    pub fn comm_seconds(&self) -> f64 {
        self.busy.get()
    }

    /// Runs one collective `f`, adding its time to [`ProcessGroup::comm_seconds`].
    fn timed<T>(&self, f: impl FnOnce() -> T) -> T {
        let start = std::time::Instant::now();
        let out = f();
        self.busy.set(self.busy.get() + start.elapsed().as_secs_f64());
        out
    }

    /// Sums (or averages) each of `tensors` over all ranks, in place. Consecutive tensors of
    /// one dtype and device are flattened into buckets of at most `bucket_bytes` (a larger
    /// tensor is a bucket of its own), one collective each.
    pub fn all_reduce(&self, tensors: &[Tensor], op: Reduce, bucket_bytes: usize) -> Result<()> {
        if op == Reduce::Average && tensors.iter().any(|t| !t.is_floating_point()) {
            return Err(Error::Invalid("averaging needs floating-point tensors".into()));
        }
        let world = self.world as f64;
        self.bucketed(tensors, bucket_bytes, |bucket| {
            self.timed(|| ffi::all_reduce_sum(&self.raw, bucket)).map_err(|why| self.failed("all-reduce", why))?;
            if op == Reduce::Average {
                let _ = bucket.divide_scalar_(world);
            }
            Ok(())
        })
    }

    /// Overwrites each of `tensors` on every rank with rank `root`'s, in buckets as
    /// [`ProcessGroup::all_reduce`].
    pub fn broadcast(&self, tensors: &[Tensor], root: usize, bucket_bytes: usize) -> Result<()> {
        if root >= self.world {
            return Err(Error::Invalid(format!("broadcast from rank {root} of a group of {}", self.world)));
        }
        self.bucketed(tensors, bucket_bytes, |bucket| {
            self.timed(|| ffi::broadcast(&self.raw, bucket, root)).map_err(|why| self.failed("broadcast", why))
        })
    }

    /// From now on, collectives on CUDA tensors run in an NCCL group beside the Gloo one
    /// (every rank must call it; CPU tensors stay with Gloo). An error naming what is
    /// missing in a build without NCCL.
    pub fn use_nccl_for_cuda(&self) -> Result<()> {
        ffi::add_nccl(&self.raw, self.timeout).map_err(|why| {
            Error::Distributed(format!("rank {} of {} could not make its NCCL group: {why}", self.rank, self.world))
        })
    }

    /// Returns when every rank has called it.
    pub fn barrier(&self) -> Result<()> {
        self.timed(|| ffi::barrier(&self.raw)).map_err(|why| self.failed("barrier", why))
    }

    /// A failed collective, with what Gloo's message means for the run: a peer gone (its
    /// connection closed) or silent past the timeout. Gloo names the peer's address only;
    /// in a group of two the peer is the other rank.
    fn failed(&self, what: &str, why: String) -> Error {
        let peer = if self.world == 2 { format!("rank {}", 1 - self.rank) } else { "another rank".to_string() };
        let gone = ["Connection reset", "Connection closed", "Broken pipe", "Connection refused", "EOF"];
        let meaning = if why.contains("Timed out") {
            format!("{peer} did not answer within the timeout of {:.0?} (stopped, hung or dead): ", self.timeout)
        } else if gone.iter().any(|g| why.contains(g)) {
            format!("{peer} is gone (its process died or its connection broke): ")
        } else {
            String::new()
        };
        Error::Distributed(format!("{what} on rank {} of {} failed: {meaning}{why}", self.rank, self.world))
    }

    /// Runs `f` on each bucket of `tensors` (flattened, concatenated, contiguous), then
    /// copies the bucket's values back.
    fn bucketed(
        &self,
        tensors: &[Tensor],
        bucket_bytes: usize,
        mut f: impl FnMut(&mut Tensor) -> Result<()>,
    ) -> Result<()> {
        let bytes = |t: &Tensor| t.numel() * t.kind().elt_size_in_bytes();
        tch::no_grad(|| {
            let mut start = 0;
            while start < tensors.len() {
                let (kind, device) = (tensors[start].kind(), tensors[start].device());
                let (mut end, mut size) = (start + 1, bytes(&tensors[start]));
                while end < tensors.len()
                    && tensors[end].kind() == kind
                    && tensors[end].device() == device
                    && size + bytes(&tensors[end]) <= bucket_bytes
                {
                    size += bytes(&tensors[end]);
                    end += 1;
                }
                let parts: Vec<Tensor> = tensors[start..end].iter().map(|t| t.reshape([-1])).collect();
                let mut bucket = Tensor::cat(&parts, 0).contiguous();
                f(&mut bucket)?;
                let mut offset = 0;
                for t in &tensors[start..end] {
                    let n = t.numel() as i64;
                    t.shallow_clone().copy_(&bucket.narrow(0, offset, n).view_as(t));
                    offset += n;
                }
                start = end;
            }
            Ok(())
        })
    }
}

impl Drop for ProcessGroup {
    fn drop(&mut self) {
        ffi::free(&mut self.raw);
    }
}

mod ffi {
    use super::Launch;
    use std::ffi::{c_char, c_int, c_long, c_void, CString};
    use std::time::Duration;
    use tch::Tensor;

    extern "C" {
        fn gdrf_c10d_new(
            host: *const c_char,
            port: c_int,
            rank: c_int,
            world: c_int,
            bind_host: *const c_char,
            timeout_ms: c_long,
            err: *mut c_char,
            err_len: usize,
        ) -> *mut c_void;
        fn gdrf_c10d_allreduce_sum(group: *mut c_void, tensor: *mut c_void, err: *mut c_char, err_len: usize) -> c_int;
        fn gdrf_c10d_broadcast(
            group: *mut c_void,
            tensor: *mut c_void,
            root: c_int,
            err: *mut c_char,
            err_len: usize,
        ) -> c_int;
        fn gdrf_c10d_barrier(group: *mut c_void, err: *mut c_char, err_len: usize) -> c_int;
        fn gdrf_c10d_add_nccl(group: *mut c_void, timeout_ms: c_long, err: *mut c_char, err_len: usize) -> c_int;
        fn gdrf_c10d_free(group: *mut c_void);
    }

    #[derive(Debug)]
    pub struct Raw(*mut c_void);

    const ERR_LEN: usize = 4096;

    /// Calls `f` with an error buffer; its message when `f` reports failure.
    fn call(f: impl FnOnce(*mut c_char, usize) -> bool) -> Result<(), String> {
        let mut buf = vec![0u8; ERR_LEN];
        if f(buf.as_mut_ptr().cast(), ERR_LEN) {
            return Ok(());
        }
        let end = buf.iter().position(|&b| b == 0).unwrap_or(ERR_LEN);
        Err(String::from_utf8_lossy(&buf[..end]).trim().to_string())
    }

    pub fn new(launch: &Launch, bind: &str, timeout: Duration) -> Result<Raw, String> {
        let host = CString::new(launch.master_addr.as_str()).map_err(|_| "MASTER_ADDR holds a NUL byte".to_string())?;
        let bind = CString::new(bind).expect("no NUL");
        let mut raw = std::ptr::null_mut();
        call(|err, len| {
            // SAFETY: the strings outlive the call; the shim writes at most `len` bytes to `err`.
            raw = unsafe {
                gdrf_c10d_new(
                    host.as_ptr(),
                    launch.master_port as c_int,
                    launch.rank as c_int,
                    launch.world as c_int,
                    bind.as_ptr(),
                    timeout.as_millis().min(c_long::MAX as u128) as c_long,
                    err,
                    len,
                )
            };
            !raw.is_null()
        })?;
        Ok(Raw(raw))
    }

    pub fn all_reduce_sum(g: &Raw, t: &mut Tensor) -> Result<(), String> {
        // SAFETY: `t` is a live tensor (tch's pointer is an at::Tensor*); `g` a live group.
        call(|err, len| unsafe { gdrf_c10d_allreduce_sum(g.0, t.as_mut_ptr().cast(), err, len) == 0 })
    }

    pub fn broadcast(g: &Raw, t: &mut Tensor, root: usize) -> Result<(), String> {
        // SAFETY: as in all_reduce_sum.
        call(|err, len| unsafe { gdrf_c10d_broadcast(g.0, t.as_mut_ptr().cast(), root as c_int, err, len) == 0 })
    }

    pub fn barrier(g: &Raw) -> Result<(), String> {
        // SAFETY: `g` is a live group.
        call(|err, len| unsafe { gdrf_c10d_barrier(g.0, err, len) == 0 })
    }

    pub fn add_nccl(g: &Raw, timeout: Duration) -> Result<(), String> {
        let ms = timeout.as_millis().min(c_long::MAX as u128) as c_long;
        // SAFETY: `g` is a live group.
        call(|err, len| unsafe { gdrf_c10d_add_nccl(g.0, ms, err, len) == 0 })
    }

    pub fn free(g: &mut Raw) {
        if !g.0.is_null() {
            // SAFETY: freed once; the pointer is cleared.
            unsafe { gdrf_c10d_free(g.0) };
            g.0 = std::ptr::null_mut();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vars<'a>(pairs: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |k| pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| v.to_string())
    }

    #[test]
    fn launcher_variables_are_read_as_torchrun_sets_them() {
        let l = Launch::from_vars(vars(&[("RANK", "1"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "10.0.0.5")])).unwrap();
        assert_eq!(
            l,
            Launch { rank: 1, world: 2, local_rank: 1, master_addr: "10.0.0.5".into(), master_port: DEFAULT_PORT }
        );
        let l = Launch::from_vars(vars(&[
            ("RANK", "3"),
            ("WORLD_SIZE", "4"),
            ("LOCAL_RANK", "1"),
            ("MASTER_ADDR", "127.0.0.1"),
            ("MASTER_PORT", "29611"),
        ]))
        .unwrap();
        assert_eq!((l.rank, l.world, l.local_rank, l.master_port), (3, 4, 1, 29611));
    }

    #[test]
    fn a_bad_launcher_variable_is_an_error_naming_it() {
        let base = [("RANK", "0"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "127.0.0.1"), ("MASTER_PORT", "29500")];
        for (name, value, says) in [
            ("MASTER_ADDR", None, "MASTER_ADDR is not set"),
            ("MASTER_ADDR", Some(" "), "MASTER_ADDR is not set"),
            ("RANK", Some("2"), "RANK is 2, expected less than WORLD_SIZE (2)"),
            ("RANK", None, "RANK is not set"),
            ("RANK", Some("-1"), "RANK is '-1'"),
            ("WORLD_SIZE", Some("0"), "WORLD_SIZE is 0"),
            ("WORLD_SIZE", Some("two"), "WORLD_SIZE is 'two'"),
            ("MASTER_PORT", Some("70000"), "MASTER_PORT is 70000"),
            ("MASTER_PORT", Some("0"), "MASTER_PORT is 0"),
            ("LOCAL_RANK", Some("x"), "LOCAL_RANK is 'x'"),
        ] {
            let mut pairs: Vec<(&str, &str)> = base.iter().copied().filter(|(n, _)| *n != name).collect();
            if let Some(v) = value {
                pairs.push((name, v));
            }
            let e = Launch::from_vars(vars(&pairs)).unwrap_err().to_string();
            assert!(e.contains(says), "{name}={value:?}: {e}");
        }
    }
}
