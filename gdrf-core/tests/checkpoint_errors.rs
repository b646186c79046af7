//! Bad checkpoints give errors that name the problem: a wrong tensor shape, a truncated
//! file, a file that is no checkpoint, a missing or unexpected tensor, a flipped bit the
//! checksum catches.
mod common;

use common::TempDir;
use gdrf_core::checkpoint::{load, load_generator, save, save_generator, Header};
use gdrf_core::{Error, Generator, GeneratorConfig};
use tch::{nn, Device, Kind, Tensor};

fn small() -> GeneratorConfig {
    GeneratorConfig { mapping_hidden_dim: 12, ..GeneratorConfig::tiny() }
}

fn tensors_of(cfg: &GeneratorConfig) -> Vec<(String, Tensor)> {
    let vs = nn::VarStore::new(Device::Cpu);
    Generator::new(&vs.root(), cfg).unwrap();
    let mut v: Vec<_> = vs.variables().into_iter().collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn load_err(path: &std::path::Path) -> Error {
    match load_generator(path, Device::Cpu, Kind::Float) {
        Ok(_) => panic!("{} loaded although it is bad", path.display()),
        Err(e) => e,
    }
}

#[test]
fn wrong_shape_names_the_tensor_and_both_shapes() {
    let dir = TempDir::new("ckpt-shape").unwrap();
    let cfg = small();
    let mut t = tensors_of(&cfg);
    let i = t.iter().position(|(n, _)| n == "template.sigma_head.weight").unwrap();
    t[i].1 = Tensor::zeros([1, 15], (Kind::Float, Device::Cpu));
    let p = dir.path("shape.safetensors");
    save(&p, &t, &Header::generator(cfg, None)).unwrap();
    let e = load_err(&p);
    let msg = e.to_string();
    assert!(matches!(e, Error::ShapeMismatch { .. }), "{msg}");
    assert!(msg.contains("template.sigma_head.weight") && msg.contains("[1, 15]") && msg.contains("[1, 16]"), "{msg}");
    assert!(msg.contains("shape.safetensors"), "{msg}");
}

#[test]
fn missing_and_unexpected_tensors_are_named() {
    let dir = TempDir::new("ckpt-names").unwrap();
    let cfg = small();
    let mut t = tensors_of(&cfg);
    t.retain(|(n, _)| n != "deform.head.bias");
    let p = dir.path("missing.safetensors");
    save(&p, &t, &Header::generator(cfg.clone(), None)).unwrap();
    let msg = load_err(&p).to_string();
    assert!(msg.contains("deform.head.bias") && msg.contains("missing") && msg.contains("[4]"), "{msg}");

    let mut t = tensors_of(&cfg);
    t.push(("template.extra".into(), Tensor::zeros([2, 2], (Kind::Float, Device::Cpu))));
    let p = dir.path("extra.safetensors");
    save(&p, &t, &Header::generator(cfg, None)).unwrap();
    let msg = load_err(&p).to_string();
    assert!(msg.contains("template.extra") && msg.contains("unexpected"), "{msg}");
}

#[test]
fn truncated_file_is_reported_as_truncated() {
    let dir = TempDir::new("ckpt-trunc").unwrap();
    let cfg = small();
    let vs = nn::VarStore::new(Device::Cpu);
    Generator::new(&vs.root(), &cfg).unwrap();
    let p = dir.path("full.safetensors");
    save_generator(&p, &vs, &Header::generator(cfg, None)).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    for cut in [bytes.len() - 1, bytes.len() / 2] {
        let q = dir.path("cut.safetensors");
        std::fs::write(&q, &bytes[..cut]).unwrap();
        let e = load_err(&q);
        let msg = e.to_string();
        assert!(matches!(e, Error::NotACheckpoint { .. }), "{msg}");
        assert!(msg.contains("truncated") && msg.contains("cut.safetensors"), "{msg}");
    }
    // Shorter than the header itself.
    let q = dir.path("tiny.safetensors");
    std::fs::write(&q, &bytes[..5]).unwrap();
    assert!(matches!(load_err(&q), Error::NotACheckpoint { .. }));
}

#[test]
fn non_checkpoint_files_are_rejected() {
    let dir = TempDir::new("ckpt-junk").unwrap();
    let p = dir.path("notes.txt");
    std::fs::write(&p, "these are not the tensors you are looking for\n".repeat(10)).unwrap();
    let msg = load_err(&p).to_string();
    assert!(msg.contains("not a gdrf checkpoint") && msg.contains("notes.txt"), "{msg}");

    // A valid safetensors file without the gdrf header.
    let q = dir.path("plain.safetensors");
    Tensor::write_safetensors(&[("w", Tensor::zeros([2], (Kind::Float, Device::Cpu)))], &q).unwrap();
    let msg = load_err(&q).to_string();
    assert!(msg.contains("without the 'gdrf' header"), "{msg}");

    let missing = dir.path("absent.safetensors");
    let msg = load_err(&missing).to_string();
    assert!(msg.contains("absent.safetensors"), "{msg}");
}

#[test]
fn saving_is_atomic_and_leaves_no_temporary_files() {
    let dir = TempDir::new("ckpt-atomic").unwrap();
    let cfg = small();
    let vs = nn::VarStore::new(Device::Cpu);
    Generator::new(&vs.root(), &cfg).unwrap();
    let p = dir.path("g.safetensors");
    std::fs::write(&p, b"old").unwrap();
    save_generator(&p, &vs, &Header::generator(cfg, None)).unwrap();
    assert!(load_generator(&p, Device::Cpu, Kind::Float).is_ok());
    let names: Vec<_> = std::fs::read_dir(&dir.0).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names.len(), 1, "{names:?}");
    // Writing into a folder that does not exist fails and names the path.
    let bad = dir.path("no/such/dir/g.safetensors");
    let msg = save_generator(&bad, &vs, &Header::generator(small(), None)).unwrap_err().to_string();
    assert!(msg.contains("no/such/dir"), "{msg}");
}

/// A bit flipped in tensor data still parses as safetensors and is finite: only the
/// checksum the header carries tells. A good file loads with the header it was saved with.
#[test]
fn a_flipped_bit_in_tensor_data_is_caught_by_the_checksum() {
    let dir = TempDir::new("ckpt-flip").unwrap();
    let cfg = small();
    let p = dir.path("g.safetensors");
    let header = Header::generator(cfg.clone(), None);
    save(&p, &tensors_of(&cfg), &header).unwrap();
    assert_eq!(load(&p).unwrap().header, header, "the checksum is checked, then cleared");
    let good = std::fs::read(&p).unwrap();
    // The last byte of the file is the lowest byte of the last tensor's last element.
    let mut bad = good.clone();
    *bad.last_mut().unwrap() ^= 1;
    let q = dir.path("flipped.safetensors");
    std::fs::write(&q, &bad).unwrap();
    let e = load_err(&q);
    let msg = e.to_string();
    assert!(matches!(e, Error::NotACheckpoint { .. }), "{msg}");
    assert!(msg.contains("checksum") && msg.contains("flipped.safetensors"), "{msg}");
}
