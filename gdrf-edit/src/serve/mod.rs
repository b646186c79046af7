//! `gdrf-edit serve`: a local web server with a page to turn a generated chair, choose its
//! shape and its appearance apart (seeds, feature files, dropped photos), interpolate them,
//! and download what is on screen. The page is plain HTML, CSS and JS served by the binary
//! itself (no download from anywhere); the HTTP layer is tiny_http (a small blocking
//! server: a handful of threads is all a local viewer needs), and rendering happens on one
//! thread that owns the generator ([`engine`]), inversion on another ([`photos`]).
pub mod bench;
mod client;
mod engine;
mod params;
mod photos;

use crate::model::{self, ModelArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use engine::{Engine, Queue, Task};
use params::{ApiError, Limits, Query, SourceSpec, View};
use photos::Photos;
use std::io::Read;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use tiny_http::{Header, Method, Request, Response, Server};

/// Set by Ctrl-C: an inversion in flight stops at its next step.
static STOPPING: AtomicBool = AtomicBool::new(false);

/// Whether the server is stopping (Ctrl-C).
pub(crate) fn stopping() -> bool {
    STOPPING.load(Ordering::SeqCst)
}

const INDEX: &str = include_str!("page/index.html");
const SCRIPT: &str = include_str!("page/app.js");
const STYLE: &str = include_str!("page/style.css");

/// Threads answering HTTP requests (renders wait on the one render thread).
const HANDLERS: usize = 8;

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    model: ModelArgs,
    /// Address to listen on. The default is this machine alone; any other address lets
    /// anyone who reaches it use the server, with no authentication, and inversions are
    /// heavy on the CPU.
    #[arg(long, default_value = "127.0.0.1")]
    host: IpAddr,
    /// Port to listen on (0: any free port, printed).
    #[arg(long, default_value_t = 8470)]
    port: u16,
    /// A folder of feature files (gdrf-invert's features.safetensors, `gdrf-edit
    /// features`) the page offers as sources, by name.
    #[arg(long, value_name = "DIR")]
    features: Option<PathBuf>,
    /// The largest image side a request may ask for, in pixels.
    #[arg(long, default_value_t = 256)]
    max_resolution: i64,
    /// The most coarse samples per ray a request may ask for.
    #[arg(long, default_value_t = 64)]
    max_samples: i64,
    /// The largest photo upload accepted, in MB.
    #[arg(long, default_value_t = 8.0)]
    max_upload_mb: f64,
}

/// What every handler thread shares.
struct Shared {
    queue: Arc<Queue>,
    photos: Arc<Photos>,
    limits: Limits,
    /// The Host headers a request may carry (DNS rebinding: a page of another site that
    /// resolves its name to this address is refused).
    hosts: Vec<String>,
    features_dir: Option<PathBuf>,
    info: serde_json::Value,
}

pub fn serve(a: ServeArgs) -> Result<()> {
    if !(8..=4096).contains(&a.max_resolution) {
        bail!("--max-resolution {}: expected 8 to 4096 pixels", a.max_resolution);
    }
    if !(2..=1024).contains(&a.max_samples) {
        bail!("--max-samples {}: expected 2 to 1024", a.max_samples);
    }
    if !(a.max_upload_mb > 0.0 && a.max_upload_mb <= 1024.0) {
        bail!("--max-upload-mb {}: expected more than 0 and at most 1024", a.max_upload_mb);
    }
    if let Some(d) = &a.features {
        if !d.is_dir() {
            bail!("--features {}: not a folder", d.display());
        }
    }
    let server = Server::http((a.host, a.port)).map_err(|e| {
        anyhow::anyhow!(
            "--host {} --port {}: cannot listen there ({e}); is the port in use? choose another with --port",
            a.host,
            a.port
        )
    })?;
    let port = server.server_addr().to_ip().map(|s| s.port()).unwrap_or(a.port);
    let (model, threads) = model::open(&a.model)?;
    // The inversion thread's own copy: tensors are not shared between threads.
    let (photo_model, _) = model::open(&a.model)?;
    let dir = std::env::temp_dir().join(format!("gdrf-serve-{}-uploads", std::process::id()));
    let photos = Arc::new(
        Photos::new(dir.clone(), (a.max_upload_mb * 1e6) as usize)
            .with_context(|| format!("creating {}", dir.display()))?,
    );
    let limits = Limits {
        max_resolution: a.max_resolution,
        max_samples: a.max_samples,
        default_resolution: model.learned.resolution.clamp(8, a.max_resolution),
        default_samples: (model.learned.samples as i64).clamp(2, a.max_samples),
        fov_deg: model.camera.fov_deg,
        pitch_deg: model.camera.v_mean.to_degrees(),
    };
    let info = serde_json::json!({
        "generator": model.id,
        "learned_resolution": model.learned.resolution,
        "learned_samples": model.learned.samples,
        "default_resolution": limits.default_resolution,
        "default_samples": limits.default_samples,
        "max_resolution": limits.max_resolution,
        "max_samples": limits.max_samples,
        "max_upload_bytes": photos.max_bytes,
        "fov_deg": limits.fov_deg,
        "pitch_deg": limits.pitch_deg,
        "inversion_steps": model.photo.cfg.steps,
    });
    let mut hosts = vec![format!("127.0.0.1:{port}"), format!("localhost:{port}"), format!("[::1]:{port}")];
    let own = match a.host {
        IpAddr::V4(h) => format!("{h}:{port}"),
        IpAddr::V6(h) => format!("[{h}]:{port}"),
    };
    if !hosts.contains(&own) {
        hosts.push(own);
    }
    let shared = Arc::new(Shared {
        queue: Arc::new(Queue::default()),
        photos: photos.clone(),
        limits,
        hosts,
        features_dir: a.features.clone(),
        info,
    });

    let queue = shared.queue.clone();
    let engine = Engine::new(model, a.features.clone(), photos.clone());
    std::thread::Builder::new().name("render".into()).spawn(move || engine.run(&queue))?;
    std::thread::Builder::new().name("invert".into()).spawn(move || photos.run(photo_model))?;

    let server = Arc::new(server);
    // Ctrl-C: stop answering, cancel an inversion in flight, let a render in flight end,
    // remove the uploads and leave. The workers must be idle first: libtorch's own
    // teardown at exit breaks an operation still running on another thread.
    {
        let (server, queue, photos) = (server.clone(), shared.queue.clone(), shared.photos.clone());
        ctrlc::set_handler(move || {
            eprintln!("\nstopping");
            STOPPING.store(true, Ordering::SeqCst);
            server.unblock();
            let start = std::time::Instant::now();
            while (queue.busy() || photos.busy()) && start.elapsed().as_secs() < 30 {
                std::thread::sleep(std::time::Duration::from_millis(10));
            }
            let _ = std::fs::remove_dir_all(&dir);
            std::process::exit(0);
        })
        .context("installing the Ctrl-C handler")?;
    }
    if !a.host.is_loopback() {
        eprintln!(
            "warning: --host {} is not this machine alone: anyone who reaches it can use this server, \
             with no authentication, and photo inversions are heavy on the CPU",
            a.host
        );
    }
    let shown = match a.host {
        IpAddr::V6(h) => format!("[{h}]"),
        h => h.to_string(),
    };
    println!("gdrf-edit serve: http://{shown}:{port}/ ({threads} threads; Ctrl-C stops)");
    let handlers: Vec<_> = (0..HANDLERS)
        .map(|i| {
            let (server, shared) = (server.clone(), shared.clone());
            std::thread::Builder::new().name(format!("http-{i}")).spawn(move || {
                for req in server.incoming_requests() {
                    handle(&shared, req);
                }
            })
        })
        .collect::<std::io::Result<_>>()?;
    for h in handlers {
        let _ = h.join();
    }
    Ok(())
}

/// A panic's message.
pub(crate) fn panic_text(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic".into())
}

/// The file `name` of the `--features` folder: found among the folder's own entries, so no
/// path from a request reaches the file system.
pub(crate) fn feature_file(dir: Option<&Path>, name: &str) -> Result<PathBuf, ApiError> {
    let dir =
        dir.ok_or_else(|| ApiError::not_found(format!("features:{name}: the server has no --features folder")))?;
    feature_names(dir)
        .into_iter()
        .find(|n| n == name)
        .map(|n| dir.join(n))
        .ok_or_else(|| ApiError::not_found(format!("features:{name}: no such file in the --features folder")))
}

/// The `.safetensors` files of a folder, sorted.
fn feature_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| e.ok())
                .filter(|e| e.path().is_file())
                .filter_map(|e| e.file_name().into_string().ok())
                .filter(|n| n.ends_with(".safetensors") && !n.starts_with('.'))
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

type Reply = (u16, Vec<u8>, &'static str, Vec<(String, String)>);

fn json(status: u16, v: serde_json::Value) -> Reply {
    (status, v.to_string().into_bytes(), "application/json", Vec::new())
}

fn error(e: ApiError) -> Reply {
    json(e.status, serde_json::json!({ "error": e.message }))
}

/// Answers one request; a panic while answering it is a 500, and the thread goes on.
fn handle(shared: &Shared, mut req: Request) {
    let (status, body, kind, headers) = guarded(|| route(shared, &mut req));
    let mut response = Response::from_data(body).with_status_code(status);
    for (k, v) in std::iter::once(("Content-Type".to_string(), kind.to_string())).chain(headers) {
        if let Ok(h) = Header::from_bytes(k.as_bytes(), v.as_bytes()) {
            response.add_header(h);
        }
    }
    let _ = req.respond(response);
}

/// `answer()`, or a 500 naming the panic it ended in.
fn guarded(answer: impl FnOnce() -> Reply) -> Reply {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(answer))
        .unwrap_or_else(|p| error(ApiError { status: 500, message: format!("the server failed: {}", panic_text(&p)) }))
}

fn route(shared: &Shared, req: &mut Request) -> Reply {
    let host = req.headers().iter().find(|h| h.field.equiv("Host")).map(|h| h.value.as_str().to_string());
    match host {
        Some(h) if shared.hosts.iter().any(|ok| ok.eq_ignore_ascii_case(&h)) => {}
        other => {
            return error(ApiError {
                status: 403,
                message: format!(
                    "Host '{}' is not this server's ({}); a page of another site cannot use it",
                    other.unwrap_or_default(),
                    shared.hosts.join(", ")
                ),
            })
        }
    }
    let url = req.url().to_string();
    let path = url.split('?').next().unwrap_or("").to_string();
    let query = match Query::parse(&url) {
        Ok(q) => q,
        Err(e) => return error(e),
    };
    let result = match (req.method(), path.as_str()) {
        (Method::Get, "/") => Ok((200, INDEX.as_bytes().to_vec(), "text/html; charset=utf-8", Vec::new())),
        (Method::Get, "/app.js") => Ok((200, SCRIPT.as_bytes().to_vec(), "text/javascript; charset=utf-8", Vec::new())),
        (Method::Get, "/style.css") => Ok((200, STYLE.as_bytes().to_vec(), "text/css; charset=utf-8", Vec::new())),
        (Method::Get, "/api/info") => Ok(info(shared)),
        (Method::Get, "/api/render") => {
            View::parse(&query, &shared.limits).and_then(|v| run(shared, &query, Task::Render(v), None))
        }
        (Method::Get, "/api/export/orbit") => View::parse(&query, &shared.limits).and_then(|v| {
            let frames = query.integer("frames", 24, (2, 120), "frames")?;
            run(shared, &query, Task::Orbit(v, frames as usize), Some("orbit.gif"))
        }),
        (Method::Get, "/api/export/mesh") => View::parse(&query, &shared.limits).and_then(|v| {
            let n = query.integer("mesh_res", 96, (16, 256), "samples per axis")?;
            run(shared, &query, Task::Mesh(v, n as usize), Some("mesh.ply"))
        }),
        (Method::Get, "/api/export/features") => query
            .source("source", None)
            .and_then(|s| run(shared, &query, Task::Features(s), Some("features.safetensors"))),
        (Method::Get, "/api/export/matrix") => View::parse(&query, &shared.limits).and_then(|v| {
            let sources = matrix_sources(&query)?;
            run(shared, &query, Task::Matrix(v, sources), Some("swap-matrix.png"))
        }),
        (Method::Post, "/api/photo") => upload(shared, req),
        (Method::Get, p) if p.starts_with("/api/photo/") => p["/api/photo/".len()..]
            .parse::<u64>()
            .map_err(|_| ApiError::bad(format!("photo id '{}': not a number", &p["/api/photo/".len()..])))
            .and_then(|id| shared.photos.status(id))
            .map(|s| json(200, serde_json::to_value(s).unwrap_or_default())),
        (_, p) => Err(ApiError::not_found(format!("{} {p}: no such endpoint", req.method()))),
    };
    result.unwrap_or_else(error)
}

fn info(shared: &Shared) -> Reply {
    let mut v = shared.info.clone();
    v["features"] = serde_json::json!(shared.features_dir.as_deref().map(feature_names).unwrap_or_default());
    v["photos"] = serde_json::json!(shared.photos.done());
    v["queued"] = serde_json::json!(shared.queue.len());
    json(200, v)
}

/// `sources`: 2 to 8 comma-separated sources.
fn matrix_sources(q: &Query) -> Result<Vec<SourceSpec>, ApiError> {
    let v =
        q.get("sources").ok_or_else(|| ApiError::bad("sources: missing; expected 2 to 8 sources, comma separated"))?;
    let sources = v.split(',').map(|s| SourceSpec::parse("sources", s.trim())).collect::<Result<Vec<_>, _>>()?;
    if !(2..=8).contains(&sources.len()) {
        return Err(ApiError::bad(format!("sources '{v}': {} given, expected 2 to 8", sources.len())));
    }
    Ok(sources)
}

/// Queues `task` for the renderer (superseding the same `client`'s waiting request) and
/// waits for its answer; `download` names the file a browser saves it as.
fn run(shared: &Shared, q: &Query, task: Task, download: Option<&str>) -> Result<Reply, ApiError> {
    let client = q.get("client").filter(|c| !c.is_empty()).map(str::to_string);
    if let Some(c) = &client {
        if c.len() > 64 || !c.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '-') {
            return Err(ApiError::bad(format!("client '{c}': expected up to 64 letters, digits or '-'")));
        }
    }
    let r = shared
        .queue
        .submit(client, task)
        .recv()
        .map_err(|_| ApiError { status: 500, message: "the renderer stopped".into() })??;
    let mut headers = vec![("X-Render-Ms".to_string(), format!("{:.1}", r.millis))];
    if let Some(name) = download {
        headers.push(("Content-Disposition".into(), format!("attachment; filename=\"{name}\"")));
    }
    Ok((200, r.bytes, r.content_type, headers))
}

fn upload(shared: &Shared, req: &mut Request) -> Result<Reply, ApiError> {
    let limit = shared.photos.max_bytes;
    if req.body_length().is_some_and(|n| n > limit) {
        return Err(ApiError {
            status: 413,
            message: format!(
                "photo: {} bytes, over the server's limit of {limit} (--max-upload-mb)",
                req.body_length().unwrap_or(0)
            ),
        });
    }
    let mut bytes = Vec::new();
    // One byte past the limit is enough to know it is over.
    req.as_reader()
        .take(limit as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| ApiError::bad(format!("photo: the upload could not be read ({e})")))?;
    let id = shared.photos.upload(&bytes)?;
    Ok(json(202, serde_json::json!({ "id": id, "source": format!("photo:{id}") })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_while_answering_is_a_500_that_names_it() {
        let (status, body, kind, _) = guarded(|| panic!("a bad tensor"));
        assert_eq!((status, kind), (500, "application/json"));
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["error"], "the server failed: a bad tensor");
        assert_eq!(guarded(|| json(200, serde_json::json!({}))).0, 200);
    }

    /// Only the folder's own `.safetensors` entries are found, by their exact name.
    #[test]
    fn feature_files_are_found_among_the_folders_entries() {
        let dir = std::env::temp_dir().join(format!("gdrf-serve-features-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        for f in ["a.safetensors", "b.txt", ".hidden.safetensors", "sub/c.safetensors"] {
            std::fs::write(dir.join(f), b"x").unwrap();
        }
        assert_eq!(feature_names(&dir), ["a.safetensors"]);
        assert_eq!(feature_file(Some(&dir), "a.safetensors").unwrap(), dir.join("a.safetensors"));
        for name in ["b.txt", ".hidden.safetensors", "c.safetensors", "sub/c.safetensors", "../a.safetensors"] {
            assert_eq!(feature_file(Some(&dir), name).unwrap_err().status, 404, "{name}");
        }
        assert!(feature_file(None, "a.safetensors").unwrap_err().message.contains("no --features folder"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
