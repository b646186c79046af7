//! Photos dropped onto the page: each upload is checked (size, that it is an image), kept
//! in the server's own folder under its id (no name from the request reaches the file
//! system), and inverted on a thread of its own with gdrf-invert's defaults, on its own copy
//! of the generator, so that renders go on meanwhile. Its progress and its features are
//! asked for by id.
use super::params::ApiError;
use crate::model::{invert_photo, Model};
use gdrf_core::edit::Features;
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Condvar, Mutex};

/// Where one upload stands.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "state", rename_all = "lowercase")]
pub enum Status {
    Queued,
    Running { step: usize, steps: usize },
    Done,
    Failed { error: String },
}

struct Upload {
    status: Status,
    features: Option<Features>,
}

/// The uploads, their inversions' queue and the folder that holds them.
pub struct Photos {
    dir: PathBuf,
    /// The largest upload accepted, in bytes.
    pub max_bytes: usize,
    uploads: Mutex<(u64, BTreeMap<u64, Upload>)>,
    queue: Mutex<VecDeque<u64>>,
    ready: Condvar,
    /// Whether a photo is being inverted now.
    busy: AtomicBool,
}

impl Photos {
    pub fn new(dir: PathBuf, max_bytes: usize) -> std::io::Result<Self> {
        std::fs::create_dir_all(&dir)?;
        Ok(Self {
            dir,
            max_bytes,
            uploads: Mutex::new((0, BTreeMap::new())),
            queue: Mutex::new(VecDeque::new()),
            ready: Condvar::new(),
            busy: AtomicBool::new(false),
        })
    }

    fn path(&self, id: u64) -> PathBuf {
        self.dir.join(format!("{id}.png"))
    }

    /// Accepts `bytes` as a photo to invert and returns its id: over the size limit is a
    /// 413, anything the image decoder cannot read a 415, both naming the upload.
    pub fn upload(&self, bytes: &[u8]) -> Result<u64, ApiError> {
        if bytes.len() > self.max_bytes {
            return Err(ApiError {
                status: 413,
                message: format!(
                    "photo: {} bytes, over the server's limit of {} (--max-upload-mb)",
                    bytes.len(),
                    self.max_bytes
                ),
            });
        }
        let img = image::load_from_memory(bytes)
            .map_err(|e| ApiError { status: 415, message: format!("photo: not an image the server reads ({e})") })?;
        let mut uploads = self.uploads.lock().unwrap_or_else(|p| p.into_inner());
        let id = uploads.0;
        uploads.0 += 1;
        gdrf_core::paths::write_atomic(&self.path(id), &png(&img)?)
            .map_err(|e| ApiError { status: 500, message: format!("photo: {e}") })?;
        uploads.1.insert(id, Upload { status: Status::Queued, features: None });
        drop(uploads);
        self.queue.lock().unwrap_or_else(|p| p.into_inner()).push_back(id);
        self.ready.notify_one();
        Ok(id)
    }

    /// Where upload `id` stands (404 for an unknown id).
    pub fn status(&self, id: u64) -> Result<Status, ApiError> {
        let uploads = self.uploads.lock().unwrap_or_else(|p| p.into_inner());
        uploads.1.get(&id).map(|u| u.status.clone()).ok_or_else(|| unknown(id))
    }

    /// The features of upload `id`, once inverted.
    pub fn features(&self, id: u64) -> Result<Features, ApiError> {
        let uploads = self.uploads.lock().unwrap_or_else(|p| p.into_inner());
        let u = uploads.1.get(&id).ok_or_else(|| unknown(id))?;
        match (&u.features, &u.status) {
            (Some(f), _) => Ok(f.shallow_clone()),
            (None, Status::Failed { error }) => {
                Err(ApiError { status: 422, message: format!("photo:{id}: its inversion failed: {error}") })
            }
            // 425 Too Early, not 409: the page takes a 409 for its own superseded request.
            (None, _) => Err(ApiError { status: 425, message: format!("photo:{id}: still being inverted") }),
        }
    }

    /// Whether a photo is being inverted now.
    pub fn busy(&self) -> bool {
        self.busy.load(Ordering::SeqCst)
    }

    /// Ids of the photos inverted so far.
    pub fn done(&self) -> Vec<u64> {
        let uploads = self.uploads.lock().unwrap_or_else(|p| p.into_inner());
        uploads.1.iter().filter(|(_, u)| u.features.is_some()).map(|(id, _)| *id).collect()
    }

    fn set(&self, id: u64, status: Status, features: Option<Features>) {
        let mut uploads = self.uploads.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(u) = uploads.1.get_mut(&id) {
            u.status = status;
            u.features = features;
        }
    }

    /// Inverts the queued photos, one at a time, for ever (the server's inversion thread).
    pub fn run(&self, model: Model) {
        loop {
            let id = {
                let mut q = self.queue.lock().unwrap_or_else(|p| p.into_inner());
                loop {
                    if let Some(id) = q.pop_front() {
                        break id;
                    }
                    q = self.ready.wait(q).unwrap_or_else(|p| p.into_inner());
                }
            };
            self.busy.store(true, Ordering::SeqCst);
            let steps = model.photo.cfg.steps;
            self.set(id, Status::Running { step: 0, steps }, None);
            let flag = format!("photo:{id}");
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                invert_photo(&model, &self.path(id), &flag, &mut |log| {
                    if super::stopping() {
                        // Unwinds out of the inversion (caught just above), without the
                        // panic hook's message: the server is stopping.
                        std::panic::resume_unwind(Box::new("cancelled: the server is stopping"));
                    }
                    self.set(id, Status::Running { step: log.step + 1, steps }, None)
                })
            }));
            match result {
                Ok(Ok(f)) => self.set(id, Status::Done, Some(f)),
                Ok(Err(e)) => self.set(id, Status::Failed { error: format!("{e:#}") }, None),
                Err(p) => self.set(id, Status::Failed { error: super::panic_text(&p) }, None),
            }
            self.busy.store(false, Ordering::SeqCst);
        }
    }
}

fn unknown(id: u64) -> ApiError {
    ApiError::not_found(format!("photo:{id}: no such upload"))
}

fn png(img: &image::DynamicImage) -> Result<Vec<u8>, ApiError> {
    gdrf_core::io::png_bytes(&img.to_rgb8()).map_err(|e| ApiError { status: 500, message: format!("photo: {e}") })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uploads_are_checked_and_asked_for_by_id() {
        let dir = std::env::temp_dir().join(format!("gdrf-photos-test-{}", std::process::id()));
        let photos = Photos::new(dir.clone(), 4096).unwrap();
        let e = photos.upload(&[0u8; 5000]).unwrap_err();
        assert_eq!(e.status, 413);
        assert!(e.message.contains("5000 bytes") && e.message.contains("--max-upload-mb"), "{}", e.message);
        let e = photos.upload(b"GIF89a but not really").unwrap_err();
        assert_eq!(e.status, 415);
        assert!(e.message.contains("not an image"), "{}", e.message);
        let img = image::RgbImage::from_pixel(4, 4, image::Rgb([200, 10, 10]));
        let id = photos.upload(&gdrf_core::io::png_bytes(&img).unwrap()).unwrap();
        assert_eq!(photos.status(id).unwrap(), Status::Queued);
        assert_eq!(photos.features(id).unwrap_err().status, 425);
        assert_eq!(photos.status(id + 1).unwrap_err().status, 404);
        assert!(photos.done().is_empty());
        // Kept under its id alone, decoded and re-encoded as PNG.
        let kept = image::open(dir.join(format!("{id}.png"))).unwrap().to_rgb8();
        assert_eq!(kept, img);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
