//! `gdrf-edit serve-bench`: frame times of `gdrf-edit serve` as the page sees them (HTTP
//! round trips against a server on 127.0.0.1, PNG included), at several resolutions, for
//! three cases: orbiting one shape, an appearance slider with the shape fixed, and a shape
//! slider; then a load test: simulated users orbiting and changing appearances at once,
//! for a bounded time, counting errors and the server's peak memory. Writes STEM.json and
//! STEM.png (the frame times) and STEM-load.json. A benchmark: nothing here asserts a time.
use super::client::{Answer, Served};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Args)]
pub struct BenchArgs {
    /// Generator checkpoint served (default: the shipped model).
    #[arg(long, visible_alias = "generator", value_name = "FILE")]
    checkpoint: Option<PathBuf>,
    /// Image sides of the frame benchmark.
    #[arg(long, value_delimiter = ',', default_value = "32,64,128")]
    resolutions: Vec<i64>,
    /// The load test alone, without the frame benchmark.
    #[arg(long)]
    load_only: bool,
    /// Frames timed per case and resolution.
    #[arg(long, default_value_t = 24)]
    frames: usize,
    /// Simulated users of the load test (0: none).
    #[arg(long, default_value_t = 8)]
    users: usize,
    /// Seconds the load test lasts.
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Image side the load test's users ask for.
    #[arg(long, default_value_t = 64)]
    load_resolution: i64,
    /// Output stem: STEM.json, STEM.png and STEM-load.json.
    #[arg(long, default_value = "serve-bench")]
    out: PathBuf,
}

/// One case at one resolution: each frame's round trip and the renderer's own time.
#[derive(serde::Serialize)]
struct Case {
    case: &'static str,
    resolution: i64,
    /// What the frames before the timed ones cost (a grid build, a shape side), ms.
    warmup_ms: Vec<f64>,
    frames_ms: Vec<f64>,
    render_ms: Vec<f64>,
    median_ms: f64,
    p95_ms: f64,
}

#[derive(serde::Serialize)]
struct LoadReport {
    users: usize,
    seconds: f64,
    resolution: i64,
    requests: usize,
    errors: usize,
    /// The first few errors, as the server or the connection gave them.
    error_samples: Vec<String>,
    requests_per_second: f64,
    latency_ms: Latency,
    /// The server's peak resident memory (VmHWM) at the end.
    peak_server_mb: f64,
}

#[derive(serde::Serialize)]
struct Latency {
    p50: f64,
    p90: f64,
    p95: f64,
    p99: f64,
    max: f64,
}

fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// A timed GET that must answer 200.
fn frame(s: &Served, path: &str) -> Result<(f64, f64)> {
    let start = Instant::now();
    let a: Answer = s.get(path).with_context(|| format!("GET {path}"))?;
    let ms = start.elapsed().as_secs_f64() * 1000.0;
    if a.status != 200 {
        bail!("GET {path}: {} {}", a.status, a.text());
    }
    Ok((ms, a.header("x-render-ms").and_then(|v| v.parse().ok()).unwrap_or(f64::NAN)))
}

pub fn bench(a: BenchArgs) -> Result<()> {
    if a.frames < 2 || a.resolutions.iter().any(|&r| !(8..=1024).contains(&r)) || a.seconds <= 0.0 {
        bail!(
            "--frames {} (at least 2), --resolutions {:?} (8 to 1024) and --seconds {} (positive)",
            a.frames,
            a.resolutions,
            a.seconds
        );
    }
    let exe = std::env::current_exe().context("finding gdrf-edit itself")?;
    let max = a.resolutions.iter().copied().chain([a.load_resolution]).max().unwrap_or(64).to_string();
    let mut args = vec!["--max-resolution", max.as_str()];
    let checkpoint = a.checkpoint.as_ref().map(|c| c.display().to_string());
    if let Some(c) = &checkpoint {
        args.extend(["--checkpoint", c.as_str()]);
    }
    let s = Served::start(&exe, &args).context("starting gdrf-edit serve")?;
    let info: serde_json::Value = serde_json::from_slice(&s.get("/api/info")?.body)?;
    let samples = info["default_samples"].as_i64().unwrap_or(12);
    let stem = a.out.display().to_string();
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut cases = Vec::new();
    let n = a.frames;
    let resolutions = if a.load_only { &[][..] } else { &a.resolutions[..] };
    for (i, &res) in resolutions.iter().enumerate() {
        let q = |rest: String| format!("/api/render?res={res}&samples={samples}&{rest}");
        // Seeds of their own at each resolution: a grid (resolution-free) or a cached
        // feature set of an earlier resolution would skip the work a user's first frames do.
        let seed = |k: usize| 20 + 10 * i + k;
        // Orbiting: the first frame renders along the whole ray, the second builds the
        // shape's grid.
        let orbit: Vec<String> = (0..n + 2).map(|k| q(format!("shape=seed:{}&yaw={}", seed(0), 15 * k))).collect();
        // The appearance slider at a fixed view: the second frame keeps the shape side.
        let slide = |key: &str, b: &str, k: usize| format!("{key}_b={b}&{key}_t={:.4}", k as f64 / (n - 1) as f64);
        let appearance: Vec<String> = (0..n + 2)
            .map(|k| {
                q(format!(
                    "shape=seed:{s}&appearance=seed:{s}&{}&yaw=30",
                    slide("appearance", &format!("seed:{}", seed(2)), k.saturating_sub(2)),
                    s = seed(1)
                ))
            })
            .collect();
        // The shape slider: every frame a new shape, its grid built.
        let shape: Vec<String> = (0..n)
            .map(|k| q(format!("shape=seed:{}&{}&yaw=30", seed(3), slide("shape", &format!("seed:{}", seed(4)), k))))
            .collect();
        for (case, paths, warm) in
            [("orbit", orbit, 2), ("appearance slider", appearance, 2), ("shape slider", shape, 0)]
        {
            let times = paths.iter().map(|p| frame(&s, p)).collect::<Result<Vec<_>>>()?;
            let (w, t) = times.split_at(warm);
            let frames_ms: Vec<f64> = t.iter().map(|x| x.0).collect();
            let c = Case {
                case,
                resolution: res,
                warmup_ms: w.iter().map(|x| x.0).collect(),
                median_ms: quantile(&frames_ms, 0.5),
                p95_ms: quantile(&frames_ms, 0.95),
                render_ms: t.iter().map(|x| x.1).collect(),
                frames_ms,
            };
            println!(
                "{res:>4}² {case:<18} median {:>7.1} ms, p95 {:>7.1} ms (renderer {:.1} ms){}",
                c.median_ms,
                c.p95_ms,
                quantile(&c.render_ms, 0.5),
                if c.warmup_ms.is_empty() {
                    String::new()
                } else {
                    format!("; first frames {:?} ms", c.warmup_ms.iter().map(|m| m.round()).collect::<Vec<_>>())
                }
            );
            cases.push(c);
        }
    }
    if !cases.is_empty() {
        let doc = serde_json::json!({
            "title": "gdrf-edit serve: frame times over HTTP on 127.0.0.1 (PNG included)",
            "machine": format!("{} CPU threads", std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)),
            "generator": info["generator"],
            "samples_per_ray": samples,
            "frames": n,
            "cases": cases,
        });
        gdrf_core::bench::write_json(std::path::Path::new(&format!("{stem}.json")), &doc)?;
        let bars = gdrf_core::plot::Bars {
            title: "gdrf-edit serve: ms a frame over HTTP (median, 95th percentile)".into(),
            y_label: "ms a frame".into(),
            groups: cases.iter().map(|c| format!("{} {}²", c.case, c.resolution)).collect(),
            series: vec![
                ("median".into(), cases.iter().map(|c| c.median_ms).collect()),
                ("95th percentile".into(), cases.iter().map(|c| c.p95_ms).collect()),
            ],
        };
        gdrf_core::io::save_png(
            std::path::Path::new(&format!("{stem}.png")),
            &gdrf_core::plot::draw_bars(&bars, 1100, 460)?,
        )?;
        println!("wrote {stem}.json and {stem}.png");
    }
    if a.users > 0 {
        let report = load(&s, &a, samples)?;
        println!(
            "load: {} users, {:.0} s at {}²: {} requests ({:.1}/s), {} errors, latency p50 {:.0} ms, p95 {:.0} ms, p99 {:.0} ms, max {:.0} ms; server peak {:.0} MB",
            report.users,
            report.seconds,
            report.resolution,
            report.requests,
            report.requests_per_second,
            report.errors,
            report.latency_ms.p50,
            report.latency_ms.p95,
            report.latency_ms.p99,
            report.latency_ms.max,
            report.peak_server_mb
        );
        gdrf_core::bench::write_json(std::path::Path::new(&format!("{stem}-load.json")), &report)?;
        println!("wrote {stem}-load.json");
    }
    Ok(())
}

/// `users` threads, each its own page (client id): orbiting in steps of 10°, and every
/// fourth request another appearance at the same view, until the time is up; a request in
/// flight then is let finish.
fn load(s: &Served, a: &BenchArgs, samples: i64) -> Result<LoadReport> {
    let stop = Arc::new(AtomicBool::new(false));
    let start = Instant::now();
    let (port, host, res) = (s.port, s.host(), a.load_resolution);
    let users: Vec<_> = (0..a.users)
        .map(|u| {
            let (stop, host) = (stop.clone(), host.clone());
            std::thread::spawn(move || {
                let (mut times, mut errors) = (Vec::new(), Vec::new());
                let mut k = 0usize;
                while !stop.load(Ordering::Relaxed) {
                    let view = k - k / 4;
                    let path = format!(
                        "/api/render?client=user-{u}&res={res}&samples={samples}&shape=seed:{}&appearance=seed:{}&yaw={}",
                        30 + u,
                        40 + u + k / 4,
                        10 * view
                    );
                    let t = Instant::now();
                    match super::client::request(port, "GET", &path, &host, &[]) {
                        Ok(r) if r.status == 200 => times.push(t.elapsed().as_secs_f64() * 1000.0),
                        Ok(r) => errors.push(format!("{} {}", r.status, r.text())),
                        Err(e) => errors.push(e.to_string()),
                    }
                    k += 1;
                }
                (times, errors)
            })
        })
        .collect();
    std::thread::sleep(Duration::from_secs_f64(a.seconds));
    stop.store(true, Ordering::Relaxed);
    let (mut times, mut errors) = (Vec::new(), Vec::new());
    for u in users {
        let (t, e) = u.join().map_err(|_| anyhow::anyhow!("a simulated user panicked"))?;
        times.extend(t);
        errors.extend(e);
    }
    let elapsed = start.elapsed().as_secs_f64();
    Ok(LoadReport {
        users: a.users,
        seconds: elapsed,
        resolution: res,
        requests: times.len() + errors.len(),
        errors: errors.len(),
        error_samples: errors.into_iter().take(5).collect(),
        requests_per_second: times.len() as f64 / elapsed,
        latency_ms: Latency {
            p50: quantile(&times, 0.5),
            p90: quantile(&times, 0.9),
            p95: quantile(&times, 0.95),
            p99: quantile(&times, 0.99),
            max: quantile(&times, 1.0),
        },
        peak_server_mb: s.peak_mb().unwrap_or(f64::NAN),
    })
}
