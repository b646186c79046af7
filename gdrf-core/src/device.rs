//! Device choice (CUDA when present, else CPU, or what the user asks for) and threads.
use crate::{Error, Result};
use tch::Device;

/// Checks that `request` is one of `auto`, `cpu`, `cuda`, `gpu` or `cuda:N` without
/// asking libtorch which devices exist (config validation on any machine).
pub fn select_syntax(request: &str) -> Result<()> {
    parse(request).map(|_| ())
}

/// Parses `auto`, `cpu`, `cuda` or `cuda:N`. `auto` picks CUDA device 0 when libtorch
/// sees one. Asking for CUDA on a machine without it is an error, not a silent fallback.
pub fn select(request: &str) -> Result<Device> {
    let device = parse(request)?;
    if let Device::Cuda(i) = device {
        let n = tch::Cuda::device_count() as usize;
        if i >= n {
            return Err(Error::Invalid(format!("device '{request}': libtorch sees {n} CUDA device(s)")));
        }
    }
    Ok(device)
}

fn parse(request: &str) -> Result<Device> {
    Ok(match request.trim().to_ascii_lowercase().as_str() {
        "auto" => Device::cuda_if_available(),
        "cpu" => Device::Cpu,
        "cuda" | "gpu" => Device::Cuda(0),
        other => match other.strip_prefix("cuda:").map(str::parse::<usize>) {
            Some(Ok(i)) => Device::Cuda(i),
            _ => return Err(Error::Invalid(format!("device '{request}': expected auto, cpu, cuda or cuda:N"))),
        },
    })
}

/// Uses every core the process may run on for libtorch's intra-op pool.
pub fn init_threads() -> usize {
    let n = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    tch::set_num_threads(n as i32);
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_requests_and_rejects_garbage() {
        assert_eq!(select("cpu").unwrap(), Device::Cpu);
        assert!(select("auto").is_ok());
        let err = select("tpu").unwrap_err().to_string();
        assert!(err.contains("tpu") && err.contains("cuda:N"), "{err}");
        if !tch::Cuda::is_available() {
            assert!(select("cuda:0").is_err());
        }
    }
}
