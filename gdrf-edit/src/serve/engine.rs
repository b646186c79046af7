//! The server's renderer: one thread owns the generator (libtorch tensors are not shared
//! between threads) and takes jobs from a queue in which a client's newer request
//! supersedes its older ones still waiting, so that a drag never waits behind stale frames.
//! It keeps what the renderer would otherwise recompute: the occupancy grid of each shape
//! asked for twice in a row (an orbit pays its build once; a shape slider's frames, each a
//! new shape, render without one), and the shape side of the last view asked for twice, so
//! that an appearance change at a fixed view only re-shades.
use super::params::{ApiError, SourceSpec, View};
use super::photos::Photos;
use crate::mesh_cmd::{self, Colour};
use crate::model::Model;
use gdrf_core::camera::{Poses, Rays};
use gdrf_core::edit::{interpolate, latents, Features, Interpolate};
use gdrf_core::render::{GridConfig, Grids, Noise, OccupancyGrid, Renderer, ShapeSide};
use gdrf_core::{io, RenderConfig};
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;
use tch::{Kind, Tensor};

/// Grids kept (a 64³ grid is 32 KB of booleans; its build is what is saved).
const GRIDS_KEPT: usize = 32;
/// Feature sets kept (seeds, files and photos, each a few KB).
const FEATURES_KEPT: usize = 256;
/// A kept shape side shades only its samples of more weight than this: each pixel then
/// differs from shading them all by at most this times the samples skipped along its ray
/// (`render::staged`), under 0.003 with 24 samples, less than one 8-bit level.
const SHADE_MIN_WEIGHT: f64 = 1e-4;

/// What a job asks the renderer for.
pub enum Task {
    /// A PNG of one view.
    Render(View),
    /// An animated GIF of `frames` views turning about the vertical axis from the view's yaw.
    Orbit(View, usize),
    /// A PLY mesh of the view's shape coloured by its appearance (`resolution`³ samples).
    Mesh(View, usize),
    /// The feature file of one source.
    Features(SourceSpec),
    /// A swap matrix of sources at the view: row i has the shape of source i, column j the
    /// appearance of source j.
    Matrix(View, Vec<SourceSpec>),
}

/// A finished job: bytes, their content type, and the renderer's milliseconds.
pub struct Reply {
    pub bytes: Vec<u8>,
    pub content_type: &'static str,
    pub millis: f64,
}

pub type Answer = Result<Reply, ApiError>;

struct Job {
    client: Option<String>,
    task: Task,
    reply: mpsc::Sender<Answer>,
}

/// The jobs waiting for the renderer, oldest first, and whether it is rendering one.
#[derive(Default)]
pub struct Queue {
    jobs: Mutex<VecDeque<Job>>,
    ready: Condvar,
    busy: AtomicBool,
}

impl Queue {
    /// Queues `task` and returns where its answer will come. A job of the same `client`
    /// still waiting is answered 409 (superseded) and dropped.
    pub fn submit(&self, client: Option<String>, task: Task) -> mpsc::Receiver<Answer> {
        let (tx, rx) = mpsc::channel();
        let mut jobs = self.jobs.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(c) = &client {
            jobs.retain(|j| {
                let stale = j.client.as_ref() == Some(c);
                if stale {
                    let _ = j.reply.send(Err(ApiError {
                        status: 409,
                        message: format!("superseded by a newer request of client {c}"),
                    }));
                }
                !stale
            });
        }
        jobs.push_back(Job { client, task, reply: tx });
        self.ready.notify_one();
        rx
    }

    /// The oldest job, waiting for one; the renderer is busy from then until the next call.
    fn next(&self) -> Job {
        self.busy.store(false, Ordering::SeqCst);
        let mut jobs = self.jobs.lock().unwrap_or_else(|p| p.into_inner());
        loop {
            if let Some(j) = jobs.pop_front() {
                self.busy.store(true, Ordering::SeqCst);
                return j;
            }
            jobs = self.ready.wait(jobs).unwrap_or_else(|p| p.into_inner());
        }
    }

    /// Whether the renderer is answering a job now.
    pub fn busy(&self) -> bool {
        self.busy.load(Ordering::SeqCst)
    }

    /// Jobs waiting for the renderer.
    pub fn len(&self) -> usize {
        self.jobs.lock().unwrap_or_else(|p| p.into_inner()).len()
    }
}

/// The renderer's state: the model and its caches.
pub struct Engine {
    pub model: Model,
    /// The `--features` folder.
    pub features_dir: Option<PathBuf>,
    pub photos: Arc<Photos>,
    features: VecDeque<(SourceSpec, Features)>,
    grids: VecDeque<(String, OccupancyGrid)>,
    /// The last view's key, and the shape side of a view asked for twice in a row.
    last_view: Option<String>,
    /// The last shape rendered: a shape asked for twice in a row gets a grid.
    last_shape: Option<String>,
    side: Option<(String, Vec<ShapeSide>)>,
}

fn internal(e: impl std::fmt::Display) -> ApiError {
    ApiError { status: 500, message: format!("{e:#}") }
}

impl Engine {
    pub fn new(model: Model, features_dir: Option<PathBuf>, photos: Arc<Photos>) -> Self {
        Self {
            model,
            features_dir,
            photos,
            features: VecDeque::new(),
            grids: VecDeque::new(),
            last_view: None,
            last_shape: None,
            side: None,
        }
    }

    /// Takes jobs from `queue` for ever (the server's render thread).
    pub fn run(mut self, queue: &Queue) {
        loop {
            let job = queue.next();
            let start = Instant::now();
            let answer = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.answer(&job.task)))
                .unwrap_or_else(|p| Err(internal(format!("the renderer failed: {}", super::panic_text(&p)))));
            let millis = start.elapsed().as_secs_f64() * 1000.0;
            let _ = job.reply.send(answer.map(|r| Reply { millis, ..r }));
        }
    }

    fn answer(&mut self, task: &Task) -> Answer {
        match task {
            Task::Render(v) => {
                let img = self.render(v)?;
                Ok(Reply { bytes: io::png_bytes(&img).map_err(internal)?, content_type: "image/png", millis: 0.0 })
            }
            Task::Orbit(v, frames) => {
                let frames = (0..*frames)
                    .map(|k| self.render(&View { yaw: v.yaw + 360.0 * k as f64 / *frames as f64, ..v.clone() }))
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(Reply {
                    bytes: io::gif_bytes(&frames, 80).map_err(internal)?,
                    content_type: "image/gif",
                    millis: 0.0,
                })
            }
            Task::Mesh(v, resolution) => {
                let (shape, appearance) =
                    (self.blend(&v.shape, &v.shape_blend)?, self.blend(&v.appearance, &v.appearance_blend)?);
                let g = &self.model.generator;
                let lat = latents(g, &shape, &appearance, g.truncation_at(v.psi).as_ref());
                let (mesh, _) = mesh_cmd::build(&self.model, &lat, (*resolution, None), Colour::Rgb)
                    .map_err(|e| ApiError { status: 422, message: format!("mesh: {e:#}") })?;
                Ok(Reply { bytes: mesh.to_ply().into_bytes(), content_type: "application/x-ply", millis: 0.0 })
            }
            Task::Features(s) => {
                let bytes = self.features_of(s)?.to_bytes(&self.model.id).map_err(internal)?;
                Ok(Reply { bytes, content_type: "application/octet-stream", millis: 0.0 })
            }
            Task::Matrix(v, sources) => {
                let mut cells = Vec::new();
                for s in sources {
                    for a in sources {
                        let view = View {
                            shape: s.clone(),
                            shape_blend: None,
                            appearance: a.clone(),
                            appearance_blend: None,
                            ..v.clone()
                        };
                        cells.push(self.render_tensor(&view)?);
                    }
                }
                let grid = io::grid(&Tensor::cat(&cells, 0), sources.len() as i64);
                let img = io::to_rgb8(&grid, false).map_err(internal)?;
                Ok(Reply { bytes: io::png_bytes(&img).map_err(internal)?, content_type: "image/png", millis: 0.0 })
            }
        }
    }

    /// The features of one source, from the cache or resolved now.
    fn features_of(&mut self, s: &SourceSpec) -> Result<Features, ApiError> {
        if let Some((_, f)) = self.features.iter().find(|(k, _)| k == s) {
            return Ok(f.shallow_clone());
        }
        let g = &self.model.generator;
        let f = match s {
            SourceSpec::Seed(n) => Features::from_seed(g, *n),
            SourceSpec::Features(name) => {
                let path = super::feature_file(self.features_dir.as_deref(), name)?;
                Features::load(&path, g, &self.model.id)
                    .map_err(|e| ApiError { status: 422, message: format!("features:{name}: {e}") })?
            }
            SourceSpec::Photo(id) => self.photos.features(*id)?,
        };
        if self.features.len() >= FEATURES_KEPT {
            self.features.pop_front();
        }
        self.features.push_back((s.clone(), f.shallow_clone()));
        Ok(f)
    }

    /// One source, or a fraction of the way from it to another.
    fn blend(&mut self, a: &SourceSpec, b: &Option<(SourceSpec, f64)>) -> Result<Features, ApiError> {
        let fa = self.features_of(a)?;
        match b {
            None => Ok(fa),
            Some((b, t)) => {
                let fb = self.features_of(b)?;
                Ok(interpolate(&self.model.generator, &fa, &fb, *t, Interpolate::Both))
            }
        }
    }

    fn render(&mut self, v: &View) -> Result<image::RgbImage, ApiError> {
        let t = self.render_tensor(v)?;
        io::to_rgb8(&t.get(0), false).map_err(internal)
    }

    /// One view `(1, 3, res, res)` in [−1, 1]: re-shaded from the kept shape side when it
    /// is this view's, else inside the shape's occupancy grid, or, for a shape seen for the
    /// first time, along the whole ray; a view asked for twice in a row keeps its shape
    /// side, so that the appearance changes after it only re-shade.
    fn render_tensor(&mut self, v: &View) -> Result<Tensor, ApiError> {
        let shape = self.blend(&v.shape, &v.shape_blend)?;
        let appearance = self.blend(&v.appearance, &v.appearance_blend)?;
        let m = &self.model;
        let g = &m.generator;
        let lat = latents(g, &shape, &appearance, g.truncation_at(v.psi).as_ref());
        let camera = gdrf_core::CameraConfig { fov_deg: v.fov, ..m.camera.clone() };
        let config = RenderConfig { num_steps: v.samples as usize, jitter: false, ..RenderConfig::default() };
        let renderer = Renderer::new(g, &camera, &config).map_err(internal)?;
        let poses = Poses::from_angles(&[(v.pitch.to_radians(), v.yaw.to_radians())], Kind::Float, m.device);
        let res = v.resolution;
        let noise = Noise::midpoints(1, res * res, v.samples, m.device);
        let view_key = format!("{} {} {} {} {res} {}", v.shape_key(), v.yaw, v.pitch, v.fov, v.samples);
        let twice = self.last_view.as_deref() == Some(view_key.as_str());
        self.last_view = Some(view_key.clone());
        if self.side.as_ref().is_none_or(|(k, _)| k != &view_key) && twice {
            let rays = Rays::from_poses(&poses, res, camera.fov_deg);
            let sides = renderer.staged().shape_sides(&lat.shape, &rays, &noise, SHADE_MIN_WEIGHT).map_err(internal)?;
            self.side = Some((view_key.clone(), sides));
        }
        if let Some((k, sides)) = &self.side {
            if k == &view_key {
                let pixel = renderer.staged().shade_chunks(sides, &lat.appearance).map_err(internal)?;
                return Ok(pixel.permute([0, 2, 1]).reshape([1, 3, res, res]) * 2.0 - 1.0);
            }
        }
        let key = v.shape_key();
        let kept = self.grids.iter().any(|(k, _)| k == &key);
        let again = self.last_shape.as_deref() == Some(key.as_str());
        self.last_shape = Some(key.clone());
        if !kept && !again {
            // A shape seen for the first time (a shape slider's frame): one image does not
            // pay for a grid's build; its second frame (an orbit) builds one.
            return Ok(renderer.render_image(&lat, &poses, res, &noise).map_err(internal)?.rgb);
        }
        if !kept {
            // The grid of the model's own camera: points outside its cube count as occupied,
            // so it serves every field of view.
            let base = Renderer::new(g, &m.camera, &config).map_err(internal)?;
            let cfg = GridConfig { resolution: 64, cells_only: true, ..GridConfig::default() };
            let grid = Grids::new(&base).occupancy_grid(&lat.shape, cfg).map_err(internal)?;
            if self.grids.len() >= GRIDS_KEPT {
                self.grids.pop_front();
            }
            self.grids.push_back((key.clone(), grid));
        }
        let grid = self.grids.iter().find(|(k, _)| k == &key).map(|(_, g)| g).expect("just kept");
        let (img, _) =
            Grids::new(&renderer).render_image_in_grids(&lat, &poses, res, &noise, &[grid]).map_err(internal)?;
        Ok(img.rgb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A client's newer request supersedes its older one still waiting (answered 409);
    /// other clients' requests and requests without a client keep their place.
    #[test]
    fn a_newer_request_supersedes_the_same_clients_waiting_one() {
        let q = Queue::default();
        let task = || Task::Features(SourceSpec::Seed(0));
        let a1 = q.submit(Some("a".into()), task());
        let b1 = q.submit(Some("b".into()), task());
        let n1 = q.submit(None, task());
        let a2 = q.submit(Some("a".into()), task());
        let n2 = q.submit(None, task());
        let e = a1.try_recv().expect("answered at once").err().expect("an error");
        assert_eq!(e.status, 409);
        assert!(e.message.contains("client a"), "{}", e.message);
        for rx in [&b1, &n1, &a2, &n2] {
            assert!(rx.try_recv().is_err(), "still waiting");
        }
        assert_eq!(q.len(), 4);
        let order: Vec<Option<String>> = (0..4).map(|_| q.next().client).collect();
        assert_eq!(order, [Some("b".into()), None, Some("a".into()), None]);
    }
}
