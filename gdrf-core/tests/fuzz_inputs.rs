//! Every parser a user can hand a file to, fed mutated valid files (bit flips, interesting
//! bytes and integers, insertions, deletions, truncations, duplicated chunks, spliced text
//! tokens) and hand-made hostile safetensors headers. The promise: no panic, no abort, no
//! allocation larger than the file justifies; a file that does not parse is an error that
//! names it.
//!
//! The inputs come from a fixed seed, so the suite runs the same corpus every time
//! (`GDRF_FUZZ_CASES` per parser, default 150). The longer run of docs/testing.md ("Reliability") sets
//! `GDRF_FUZZ_CASES` higher and `GDRF_FUZZ_SEED` to a new seed. A failure is shrunk by
//! proptest to a minimal list of mutations, printed with the parser's name.
mod common;

use common::TempDir;
use gdrf_core::checkpoint::{self, Header};
use gdrf_core::data::{self, folder, layouts, npy};
use gdrf_core::edit::{generator_id, Features};
use gdrf_core::train::config::TrainConfig;
use gdrf_core::{Generator, GeneratorConfig};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use tch::{nn, Device, Kind};

/// The system allocator, recording the largest single allocation (Rust's; libtorch's own
/// are bounded by the parsers' checks before any tensor is made).
struct Tracking;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Tracking {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Tracking = Tracking;

/// One parser at a time, so that the largest allocation is that parser's.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Headroom every parse may allocate whatever the file (buffers, tables, thread stacks).
const FLOOR: usize = 32 << 20;

fn cases() -> u32 {
    std::env::var("GDRF_FUZZ_CASES").map_or(150, |v| v.parse().expect("GDRF_FUZZ_CASES: a count"))
}

fn seed() -> u64 {
    std::env::var("GDRF_FUZZ_SEED").map_or(0x6764_7266, |v| v.parse().expect("GDRF_FUZZ_SEED: an integer"))
}

/// One mutation: (kind, position draw, value draw).
type Op = (u8, u64, u64);

const BYTES: [u8; 8] = [0, 0xff, 0x7f, 0x80, b'9', b'-', b'"', b'{'];
// Kept as a table: one token per line would hide which ones there are.
#[rustfmt::skip]
const TOKENS: [&str; 16] = [
    "1e309", "-1", "99999999999999999999", "nan", "\"", "[", "]", "{", "}", ",", "\n", "=", "0", "4294967296",
    "[[stages]]\n", "\"F64\"",
];

/// Applies `ops` to `seed_bytes`. Half of the positions fall in the first `head` bytes,
/// where headers and length fields are.
fn mutate(seed_bytes: &[u8], head: usize, ops: &[Op]) -> Vec<u8> {
    let mut b = seed_bytes.to_vec();
    for &(kind, p, v) in ops {
        let span = if p & 1 == 0 { head.min(b.len()) } else { b.len() };
        let pos = if span == 0 { 0 } else { (p >> 1) as usize % span };
        match kind % 8 {
            0 if !b.is_empty() => {
                let i = pos.min(b.len() - 1);
                b[i] ^= 1 << (v % 8)
            }
            1 if !b.is_empty() => {
                let i = pos.min(b.len() - 1);
                b[i] = BYTES[v as usize % BYTES.len()]
            }
            2 => {
                let n = 1 + (v % 8) as usize;
                b.splice(pos..pos, v.to_le_bytes()[..n].iter().copied());
            }
            3 => {
                let end = (pos + 1 + (v % 16) as usize).min(b.len());
                b.drain(pos.min(end)..end);
            }
            4 => b.truncate(pos),
            5 => {
                let n = [u64::MAX, u32::MAX as u64, 1 << 40, 0, i64::MAX as u64, 2 * b.len() as u64][v as usize % 6];
                let end = (pos + 8).min(b.len());
                let len = end.saturating_sub(pos);
                b[pos.min(end)..end].copy_from_slice(&n.to_le_bytes()[..len]);
            }
            6 => {
                let t = TOKENS[v as usize % TOKENS.len()].as_bytes();
                b.splice(pos..pos, t.iter().copied());
            }
            _ => {
                // A chunk copied over another place (overlapping offsets, repeated keys).
                let from = (v as usize) % b.len().max(1);
                let n = (1 + (v >> 32) as usize % 32).min(b.len() - from.min(b.len()));
                let chunk = b[from..from + n].to_vec();
                let end = (pos + n).min(b.len());
                let len = end.saturating_sub(pos);
                b[pos.min(end)..end].copy_from_slice(&chunk[..len]);
            }
        }
    }
    b
}

/// Runs `parse` on `cases()` mutations of `seed_bytes`, written to `path` (the parser reads
/// `path` or the folder it lies in). Each parse must return (Ok, or an error whose message
/// holds `path`'s file name) without panicking, and allocate no single block larger than
/// `FLOOR + per_byte · file length`. Returns how many inputs were errors.
fn fuzz(
    name: &str,
    path: &Path,
    seed_bytes: &[u8],
    head: usize,
    per_byte: usize,
    parse: impl Fn(&Path) -> Result<(), String>,
) -> usize {
    fuzz_fixed(name, path, seed_bytes, head, per_byte, |_| (), parse)
}

/// [`fuzz`], with `fix` applied to each mutated file before it is parsed (checksums made
/// right again, so that the mutation reaches the decoder behind them).
fn fuzz_fixed(
    name: &str,
    path: &Path,
    seed_bytes: &[u8],
    head: usize,
    per_byte: usize,
    fix: impl Fn(&mut [u8]),
    parse: impl Fn(&Path) -> Result<(), String>,
) -> usize {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let file = path.file_name().unwrap().to_string_lossy().into_owned();
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed().to_le_bytes());
    key[8..8 + name.len().min(24)].copy_from_slice(&name.as_bytes()[..name.len().min(24)]);
    let config = Config { cases: cases(), failure_persistence: None, ..Config::default() };
    let mut runner = TestRunner::new_with_rng(config, TestRng::from_seed(RngAlgorithm::ChaCha, &key));
    let errors = AtomicUsize::new(0);
    // The unmutated file must parse: otherwise every case would only test one error path.
    std::fs::write(path, seed_bytes).unwrap();
    if let Err(e) = parse(path) {
        panic!("{name}: the valid seed file does not parse: {e}");
    }
    let result = runner.run(&prop::collection::vec((any::<u8>(), any::<u64>(), any::<u64>()), 1..6), |ops| {
        let mut bytes = mutate(seed_bytes, head, &ops);
        fix(&mut bytes);
        std::fs::write(path, &bytes).unwrap();
        LARGEST.store(0, Ordering::Relaxed);
        let r = parse(path);
        let largest = LARGEST.load(Ordering::Relaxed);
        let bound = FLOOR + per_byte * bytes.len();
        prop_assert!(largest <= bound, "{name}: one allocation of {largest} bytes for a file of {} bytes", bytes.len());
        if let Err(msg) = r {
            errors.fetch_add(1, Ordering::Relaxed);
            prop_assert!(msg.contains(&file), "{name}: the error does not name {file}: {msg}");
        }
        Ok(())
    });
    if let Err(e) = result {
        panic!("{name} (seed {}): {e}", seed());
    }
    let n = errors.into_inner();
    println!("{name}: {} inputs, {n} refused with an error naming the file, 0 panics", cases());
    n
}

fn err_string(e: gdrf_core::Error) -> String {
    e.to_string()
}

/// A PNG or JPEG decodes to at most 16 bytes a pixel (float RGBA), from at most 8 × 1032
/// pixels a byte (deflate's largest ratio, at 1 bit a pixel).
const IMAGE_PER_BYTE: usize = 16 * 8 * 1032;

/// Recomputes every PNG chunk's CRC-32 (length, type, data, CRC from byte 8 on).
fn fix_png_crcs(b: &mut [u8]) {
    let mut pos = 8;
    while pos + 12 <= b.len() {
        let len = u32::from_be_bytes(b[pos..pos + 4].try_into().unwrap()) as usize;
        let Some(end) = (pos + 8).checked_add(len).filter(|&e| e + 4 <= b.len()) else { break };
        let crc = crc32fast::hash(&b[pos + 4..end]);
        b[end..end + 4].copy_from_slice(&crc.to_be_bytes());
        pos = end + 4;
    }
}

fn encoded(img: image::DynamicImage, format: image::ImageFormat) -> Vec<u8> {
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), format).unwrap();
    bytes
}

fn gradient(w: u32, h: u32) -> image::RgbaImage {
    image::RgbaImage::from_fn(w, h, |x, y| image::Rgba([(x * 10) as u8, (y * 15) as u8, 128, 200 + (x % 50) as u8]))
}

#[test]
fn image_files() {
    let dir = TempDir::new("fuzz-images").unwrap();
    let png = encoded(image::DynamicImage::ImageRgba8(gradient(24, 16)), image::ImageFormat::Png);
    let gray16 = encoded(
        image::DynamicImage::ImageLuma16(image::ImageBuffer::from_fn(9, 7, |x, y| {
            image::Luma([(x * 7000 + y * 300) as u16])
        })),
        image::ImageFormat::Png,
    );
    let rgb = image::DynamicImage::ImageRgba8(gradient(24, 16)).to_rgb8();
    let jpeg = encoded(image::DynamicImage::ImageRgb8(rgb), image::ImageFormat::Jpeg);
    let load = |p: &Path| folder::load_image(p, 8).map(drop).map_err(err_string);
    fuzz("png (rgba8)", &dir.path("chair.png"), &png, 64, IMAGE_PER_BYTE, load);
    fuzz("png (gray16)", &dir.path("gray.png"), &gray16, 64, IMAGE_PER_BYTE, load);
    fuzz_fixed("png (checksums fixed)", &dir.path("fixed.png"), &png, 64, IMAGE_PER_BYTE, fix_png_crcs, load);
    fuzz("jpeg", &dir.path("chair.jpg"), &jpeg, 256, IMAGE_PER_BYTE, load);
    let photo = |p: &Path| {
        gdrf_core::invert::photo::load_photo(p, None, gdrf_core::invert::photo::Fit::Pad, 8, Device::Cpu)
            .map(drop)
            .map_err(err_string)
    };
    fuzz("photo (png)", &dir.path("photo.png"), &png, 64, IMAGE_PER_BYTE, photo);
}

/// Image headers that claim far more pixels than the file holds (valid checksums, so only
/// the size tells): refused with an error naming the file, before the decoder allocates
/// the claimed image.
#[test]
fn images_claiming_more_pixels_than_their_bytes_hold() {
    let dir = TempDir::new("fuzz-huge-images").unwrap();
    let mut png = encoded(image::DynamicImage::ImageRgba8(gradient(24, 16)), image::ImageFormat::Png);
    // IHDR: length (8..12), type (12..16), width (16..20), height (20..24), …, CRC (29..33).
    png[16..20].copy_from_slice(&11_000u32.to_be_bytes());
    png[20..24].copy_from_slice(&11_000u32.to_be_bytes());
    let crc = crc32fast::hash(&png[12..29]);
    png[29..33].copy_from_slice(&crc.to_be_bytes());
    let rgb = image::DynamicImage::ImageRgba8(gradient(24, 16)).to_rgb8();
    let mut jpeg = encoded(image::DynamicImage::ImageRgb8(rgb), image::ImageFormat::Jpeg);
    // SOF0: FF C0, length, precision, height, width.
    let sof = jpeg.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
    jpeg[sof + 5..sof + 7].copy_from_slice(&11_000u16.to_be_bytes());
    jpeg[sof + 7..sof + 9].copy_from_slice(&11_000u16.to_be_bytes());
    for (name, bytes) in [("huge.png", png), ("huge.jpg", jpeg)] {
        let path = dir.path(name);
        std::fs::write(&path, &bytes).unwrap();
        let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        LARGEST.store(0, Ordering::Relaxed);
        let e = match folder::load_image(&path, 8) {
            Ok(_) => panic!("{name}: decoded"),
            Err(e) => e.to_string(),
        };
        let largest = LARGEST.load(Ordering::Relaxed);
        println!("{name} ({} bytes): {e}; largest allocation {largest} bytes", bytes.len());
        assert!(e.contains(name), "{e}");
        assert!(largest <= FLOOR + IMAGE_PER_BYTE * bytes.len(), "{name}: one allocation of {largest} bytes");
    }
}

/// A dataset folder in the authors' `camera_param` layout: the pose file mutated, then one
/// of its images.
#[test]
fn dataset_folders() {
    let dir = TempDir::new("fuzz-dataset").unwrap();
    let d = dir.path("chairs");
    std::fs::create_dir_all(&d).unwrap();
    let png = encoded(image::DynamicImage::ImageRgba8(gradient(12, 12)), image::ImageFormat::Png);
    for name in ["a.png", "b.png"] {
        std::fs::write(d.join(name), &png).unwrap();
    }
    let poses = br#"{"a.png": {"phi": 1.4, "theta": 0.3}, "b.png": {"phi": 1.6, "theta": -2.0}}"#;
    let load = |p: &Path| {
        let mut opts = data::LoadOptions::new(8);
        (opts.cache, opts.threads) = (false, 1);
        data::load(p.parent().unwrap(), &opts, &|_| ()).map(drop).map_err(err_string)
    };
    fuzz("dataset (camera_param.json)", &d.join("camera_param.json"), poses, 64, 64, load);
    std::fs::write(d.join("camera_param.json"), poses).unwrap();
    fuzz("dataset (an image)", &d.join("b.png"), &png, 64, IMAGE_PER_BYTE, load);
    let read = |p: &Path| layouts::read_camera_param(p).map(drop).map_err(err_string);
    fuzz("camera_param.json", &dir.path("camera_param.json"), poses, 64, 64, read);
}

#[test]
fn npy_pose_files() {
    let dir = TempDir::new("fuzz-npy").unwrap();
    let m = [[0.0, 0.0, 1.0, 1.2], [1.0, 0.0, 0.0, 0.3], [0.0, 1.0, 0.0, -0.5], [0.0, 0.0, 0.0, 1.0]];
    let bytes = npy::encode_matrix_f64(&m);
    let read = |p: &Path| {
        let m = npy::read_matrix(p).map_err(err_string)?;
        layouts::carla_pose(&m).map(drop).map_err(|reason| format!("{}: {reason}", p.display()))
    };
    fuzz("npy", &dir.path("0001_extrinsics.npy"), &bytes, 128, 64, read);
}

#[test]
fn training_configs() {
    let dir = TempDir::new("fuzz-toml").unwrap();
    let text = std::fs::read(common::repo_root().join("configs/chairs-tiny.toml")).unwrap();
    let load = |p: &Path| TrainConfig::load(p).map(drop).map_err(err_string);
    fuzz("toml config", &dir.path("chairs-tiny.toml"), &text, text.len(), 64, load);
}

fn tiny_generator() -> (nn::VarStore, Generator) {
    let vs = nn::VarStore::new(Device::Cpu);
    let g = Generator::new(&vs.root(), &GeneratorConfig { mapping_hidden_dim: 12, ..GeneratorConfig::tiny() }).unwrap();
    (vs, g)
}

/// The length of a safetensors file's header (its first 8 bytes and the JSON).
fn header_span(bytes: &[u8]) -> usize {
    8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize
}

#[test]
fn generator_checkpoints_and_feature_files() {
    let dir = TempDir::new("fuzz-safetensors").unwrap();
    let (vs, g) = tiny_generator();
    let ckpt = dir.path("seed.safetensors");
    checkpoint::save_generator(&ckpt, &vs, &Header::generator(g.cfg.clone(), None)).unwrap();
    let bytes = std::fs::read(&ckpt).unwrap();
    let load = |p: &Path| checkpoint::load_generator(p, Device::Cpu, Kind::Float).map(drop).map_err(err_string);
    fuzz("generator checkpoint", &dir.path("generator.safetensors"), &bytes, header_span(&bytes), 64, load);

    let id = generator_id(&vs, &g);
    let feats = dir.path("seed-features.safetensors");
    Features::from_seed(&g, 3).save(&feats, &id).unwrap();
    let bytes = std::fs::read(&feats).unwrap();
    let load = |p: &Path| Features::load(p, &g, &id).map(drop).map_err(err_string);
    fuzz("feature file", &dir.path("features.safetensors"), &bytes, header_span(&bytes), 64, load);
}

/// Safetensors headers no mutation is likely to reach: each is refused with an error
/// naming the file, before any tensor is made.
#[test]
fn hostile_safetensors_headers() {
    let dir = TempDir::new("fuzz-hostile").unwrap();
    let (vs, g) = tiny_generator();
    let seed = dir.path("seed.safetensors");
    checkpoint::save_generator(&seed, &vs, &Header::generator(g.cfg.clone(), None)).unwrap();
    let bytes = std::fs::read(&seed).unwrap();
    let span = header_span(&bytes);
    let json = std::str::from_utf8(&bytes[8..span]).unwrap().to_string();
    let with_header = |json: &str| {
        let mut b = (json.len() as u64).to_le_bytes().to_vec();
        b.extend_from_slice(json.as_bytes());
        b.extend_from_slice(&bytes[span..]);
        b
    };
    let with_length = |n: u64| {
        let mut b = bytes.clone();
        b[..8].copy_from_slice(&n.to_le_bytes());
        b
    };
    // The first tensor's entry, to rewrite its offsets, dtype or shape.
    let first = json.find("\"data_offsets\":[").unwrap();
    let offsets_end = first + json[first..].find(']').unwrap() + 1;
    let mut cases: Vec<(&str, Vec<u8>)> = vec![
        ("header length u64::MAX", with_length(u64::MAX)),
        ("header length past the end", with_length(bytes.len() as u64)),
        ("header length 0", with_length(0)),
        ("header length 1 TB", with_length(1 << 40)),
        (
            "overlapping offsets",
            with_header(&format!("{}\"data_offsets\":[0,8]{}", &json[..first], &json[offsets_end..])),
        ),
        (
            "offsets past the end",
            with_header(&format!("{}\"data_offsets\":[0,{}]{}", &json[..first], u64::MAX, &json[offsets_end..])),
        ),
        ("the file's bytes only", bytes[..span].to_vec()),
        ("8 bytes", bytes[..8].to_vec()),
        ("empty", Vec::new()),
    ];
    for (from, to) in [("\"F32\"", "\"F8_E4M3\""), ("\"F32\"", "\"BOOL\""), ("\"F32\"", "\"U64\"")] {
        cases.push(("a dtype the loaders do not take", with_header(&json.replacen(from, to, 1))));
    }
    let shape = json.find("\"shape\":[").unwrap();
    let shape_end = shape + json[shape..].find(']').unwrap() + 1;
    for s in [
        "[4294967296,4294967296]",
        "[18446744073709551615,2]",
        "[-1]",
        "[1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1,1]",
    ] {
        cases.push((
            "a shape that does not fit its bytes",
            with_header(&format!("{}\"shape\":{s}{}", &json[..shape], &json[shape_end..])),
        ));
    }
    for (key, value) in [
        ("hidden_dim", "16000000"),
        ("mapping_hidden_dim", "4000000000"),
        ("trunk_layers", "100000000"),
        ("latent_dim", "0"),
    ] {
        let gdrf = json.find(&format!("\\\"{key}\\\":")).unwrap_or_else(|| panic!("{key} not in the header"));
        let start = gdrf + key.len() + 5;
        let end = start + json[start..].find(|c: char| !c.is_ascii_digit()).unwrap();
        cases.push((
            "a generator config the tensors do not hold",
            with_header(&format!("{}{value}{}", &json[..start], &json[end..])),
        ));
    }
    let path = dir.path("hostile.safetensors");
    for (what, b) in cases {
        std::fs::write(&path, &b).unwrap();
        LARGEST.store(0, Ordering::Relaxed);
        let e = match checkpoint::load_generator(&path, Device::Cpu, Kind::Float) {
            Ok(_) => panic!("{what}: loaded"),
            Err(e) => e.to_string(),
        };
        assert!(e.contains("hostile.safetensors"), "{what}: {e}");
        let largest = LARGEST.load(Ordering::Relaxed);
        assert!(largest <= FLOOR + 64 * b.len(), "{what}: one allocation of {largest} bytes");
        println!("{what}: {e}");
    }
}

/// The inversion's initialiser files: a header whose widths the tensors do not hold is an
/// error naming the file, before the network is built.
#[test]
fn hostile_initialiser_headers() {
    let dir = TempDir::new("fuzz-init").unwrap();
    let path: PathBuf = dir.path("init.safetensors");
    for (mapping_hidden, resolution, appearance_dim) in [
        (-1i64, 64i64, 0i64),
        (1 << 40, 64, 0),
        (i64::MAX, 64, 0),
        (16, 0, 0),
        (16, -5, 0),
        (16, 1 << 40, 0),
        (16, 64, -3),
        (16, 64, i64::MAX),
        (16, 64, 1 << 40),
    ] {
        let json = serde_json::json!({
            "format_version": 2, "generator": "g", "backbone": "resnet34", "resolution": resolution,
            "mapping_hidden": mapping_hidden, "appearance_dim": appearance_dim, "step": 0, "half": false,
            "config": gdrf_core::invert::init::InitConfig::default(),
        })
        .to_string();
        let head = tch::Tensor::zeros([19, 512], (Kind::Float, Device::Cpu));
        let b = checkpoint::tensors_to_bytes(&[("head.weight".into(), head)], gdrf_core::invert::init::INIT_KEY, &json)
            .unwrap();
        std::fs::write(&path, b).unwrap();
        let e = match gdrf_core::invert::init::Initialiser::load(&path, "g", Device::Cpu) {
            Ok(_) => {
                panic!("mapping_hidden {mapping_hidden}, resolution {resolution}, appearance {appearance_dim}: loaded")
            }
            Err(e) => e.to_string(),
        };
        assert!(e.contains("init.safetensors"), "{e}");
        println!("mapping_hidden {mapping_hidden}, resolution {resolution}: {e}");
    }
}
