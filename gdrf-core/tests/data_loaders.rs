//! Loaders for real image collections: format conversion (alpha on white, grayscale,
//! palette, 16-bit, JPEG), centre crop and area resize, the authors' layouts
//! (camera_param.json, CARLA extrinsics), the cache, and every bad-input case: an
//! error naming the file, or with `skip_bad` a recorded skip.
mod common;

use common::TempDir;
use gdrf_core::data::layouts::{carla_pose, Layout, CAMERA_PARAM_FILE};
use gdrf_core::data::{self, npy, CacheStatus, Dataset, LoadOptions};
use gdrf_core::Error;
use image::{DynamicImage, ImageBuffer, ImageFormat, Luma, LumaA, Rgb, Rgba};
use std::path::{Path, PathBuf};
use tch::Tensor;

fn opts(res: usize) -> LoadOptions {
    LoadOptions { cache: false, threads: 2, ..LoadOptions::new(res) }
}

fn load(dir: &Path, o: &LoadOptions) -> gdrf_core::Result<Dataset> {
    data::load(dir, o, &|_| {})
}

/// `(H, W, 3)` bytes of image `i` of a dataset.
fn pixels(ds: &Dataset, i: i64) -> Vec<u8> {
    Vec::<u8>::try_from(ds.pixels.get(i).permute([1, 2, 0]).contiguous().view([-1])).unwrap()
}

fn solid_rgb(path: &Path, w: u32, h: u32, c: [u8; 3]) {
    ImageBuffer::from_pixel(w, h, Rgb(c)).save(path).unwrap();
}

fn assert_all_near(got: &[u8], want: [u8; 3], tol: i32, what: &str) {
    for px in got.chunks(3) {
        for c in 0..3 {
            assert!((px[c] as i32 - want[c] as i32).abs() <= tol, "{what}: got {px:?}, want {want:?}");
        }
    }
}

fn palette_png(path: &Path) {
    let file = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), 8, 8);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(vec![0u8, 0, 0, 20, 40, 220]);
    let mut w = enc.write_header().unwrap();
    w.write_image_data(&[1u8; 64]).unwrap();
}

#[test]
fn every_pixel_format_becomes_rgb_on_white() {
    let tmp = TempDir::new("load-formats").unwrap();
    let d = &tmp.0;
    solid_rgb(&d.join("a_rgb.png"), 8, 8, [10, 200, 30]);
    ImageBuffer::from_pixel(8, 8, Rgba([255u8, 0, 0, 128])).save(d.join("b_rgba.png")).unwrap();
    ImageBuffer::from_pixel(8, 8, Luma([100u8])).save(d.join("c_gray.png")).unwrap();
    ImageBuffer::from_pixel(8, 8, LumaA([0u8, 0])).save(d.join("d_gray_alpha.png")).unwrap();
    ImageBuffer::from_pixel(8, 8, Rgb([0x8080u16, 0, 0xffff])).save(d.join("e_rgb16.png")).unwrap();
    palette_png(&d.join("f_palette.png"));
    solid_rgb(&d.join("g_photo.JPG"), 8, 8, [200, 100, 50]);
    DynamicImage::ImageLuma8(ImageBuffer::from_pixel(8, 8, Luma([60u8])))
        .save_with_format(d.join("h_gray.jpeg"), ImageFormat::Jpeg)
        .unwrap();
    std::fs::write(d.join("notes.txt"), "not an image, not listed").unwrap();

    let ds = load(d, &opts(4)).unwrap();
    assert_eq!(ds.layout, Layout::Folder);
    assert_eq!(
        ds.names,
        [
            "a_rgb.png",
            "b_rgba.png",
            "c_gray.png",
            "d_gray_alpha.png",
            "e_rgb16.png",
            "f_palette.png",
            "g_photo.JPG",
            "h_gray.jpeg"
        ]
    );
    assert!(ds.poses.is_none() && ds.skipped.is_empty());
    let want: [([u8; 3], i32); 8] = [
        ([10, 200, 30], 0),
        ([255, 127, 127], 1), // 50% red over white
        ([100, 100, 100], 0),
        ([255, 255, 255], 0), // transparent → white
        ([128, 0, 255], 0),   // 16-bit 0x8080 ≈ 0.502
        ([20, 40, 220], 0),   // palette entry 1
        ([200, 100, 50], 4),  // JPEG
        ([60, 60, 60], 3),
    ];
    for (i, (w, tol)) in want.iter().enumerate() {
        assert_all_near(&pixels(&ds, i as i64), *w, *tol, &ds.names[i]);
    }
    // Training tensors: (N, 3, R, R) in [−1, 1], white exactly 1.
    let imgs = ds.images();
    assert_eq!(imgs.size(), [8, 3, 4, 4]);
    assert_eq!(f64::try_from(imgs.get(3).min()).unwrap(), 1.0);
    assert!(f64::try_from(imgs.min()).unwrap() >= -1.0);
}

#[test]
fn non_square_images_are_centre_cropped_and_any_size_is_area_resized() {
    let tmp = TempDir::new("load-crop").unwrap();
    let d = &tmp.0;
    // Wide: red | blue | green thirds → the centre square is blue.
    let wide = ImageBuffer::from_fn(30, 10, |x, _| {
        Rgb(if x < 10 {
            [255u8, 0, 0]
        } else if x < 20 {
            [0, 0, 255]
        } else {
            [0, 255, 0]
        })
    });
    wide.save(d.join("a_wide.png")).unwrap();
    let tall = ImageBuffer::from_fn(10, 30, |_, y| {
        Rgb(if y < 10 {
            [255u8, 0, 0]
        } else if y < 20 {
            [0, 0, 255]
        } else {
            [0, 255, 0]
        })
    });
    tall.save(d.join("b_tall.png")).unwrap();
    // A one-pixel checkerboard averages to mid grey.
    let checker = ImageBuffer::from_fn(64, 64, |x, y| Luma([if (x + y) % 2 == 0 { 0u8 } else { 255 }]));
    checker.save(d.join("c_checker.png")).unwrap();
    // Upscaling 2 → 4 repeats each pixel in a 2 × 2 block.
    let tiny = ImageBuffer::from_fn(2, 2, |x, y| Luma([(x * 100 + y * 50) as u8]));
    tiny.save(d.join("d_tiny.png")).unwrap();

    let ds = load(d, &opts(4)).unwrap();
    assert_all_near(&pixels(&ds, 0), [0, 0, 255], 0, "wide");
    assert_all_near(&pixels(&ds, 1), [0, 0, 255], 0, "tall");
    assert_all_near(&pixels(&ds, 2), [128, 128, 128], 1, "checker");
    let up = pixels(&ds, 3);
    let at = |x: usize, y: usize| up[(y * 4 + x) * 3];
    assert_eq!([at(0, 0), at(3, 0), at(0, 3), at(3, 3)], [0, 100, 50, 150]);
}

/// A folder with one good image and `bad`, loaded strictly: the error names `bad`.
fn assert_fails_naming(bad: &Path, make: impl FnOnce(&Path), expect: &str) {
    let dir = bad.parent().unwrap();
    std::fs::create_dir_all(dir).unwrap();
    solid_rgb(&dir.join("good.png"), 8, 8, [1, 2, 3]);
    make(bad);
    match load(dir, &opts(8)) {
        Ok(_) => panic!("{} loaded although it is bad", bad.display()),
        Err(e @ Error::Data { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains(&bad.display().to_string()) && msg.contains(expect), "{msg}");
        }
        Err(e) => panic!("expected a data error naming {}, got {e}", bad.display()),
    }
}

fn valid_png() -> Vec<u8> {
    let mut v = Vec::new();
    let img = ImageBuffer::from_fn(32, 32, |x, y| Rgb([x as u8 * 8, y as u8 * 8, 7]));
    DynamicImage::ImageRgb8(img).write_to(&mut std::io::Cursor::new(&mut v), ImageFormat::Png).unwrap();
    v
}

fn valid_jpeg() -> Vec<u8> {
    let mut v = Vec::new();
    let img = ImageBuffer::from_fn(32, 32, |x, y| Rgb([x as u8 * 8, y as u8 * 8, 7]));
    DynamicImage::ImageRgb8(img).write_to(&mut std::io::Cursor::new(&mut v), ImageFormat::Jpeg).unwrap();
    v
}

/// A bad file's path, how to make it, and what the error must say.
type BadImage = (PathBuf, Box<dyn FnOnce(&Path)>, &'static str);

fn bad_images(root: &Path) -> Vec<BadImage> {
    vec![
        (root.join("empty/x.png"), Box::new(|p: &Path| std::fs::write(p, b"").unwrap()), "empty file"),
        (
            root.join("trunc_png/x.png"),
            Box::new(|p: &Path| {
                let v = valid_png();
                std::fs::write(p, &v[..v.len() / 2]).unwrap()
            }),
            "cannot decode",
        ),
        (
            root.join("trunc_jpg/x.jpg"),
            Box::new(|p: &Path| {
                let v = valid_jpeg();
                std::fs::write(p, &v[..v.len() * 2 / 3]).unwrap()
            }),
            "truncated JPEG",
        ),
        (
            root.join("garbage/x.png"),
            Box::new(|p: &Path| std::fs::write(p, b"hello, world").unwrap()),
            "not a PNG or JPEG",
        ),
        (
            root.join("dangling/x.png"),
            Box::new(|p: &Path| std::os::unix::fs::symlink(p.with_file_name("gone.png"), p).unwrap()),
            "cannot read",
        ),
    ]
}

#[test]
fn bad_images_are_errors_naming_the_file() {
    let tmp = TempDir::new("load-bad").unwrap();
    for (bad, make, expect) in bad_images(&tmp.0) {
        assert_fails_naming(&bad, make, expect);
    }
}

#[test]
fn with_skip_bad_bad_images_are_counted_and_named() {
    let tmp = TempDir::new("load-skip").unwrap();
    let dir = tmp.path("all");
    std::fs::create_dir_all(&dir).unwrap();
    solid_rgb(&dir.join("good.png"), 8, 8, [1, 2, 3]);
    let mut bad_paths = Vec::new();
    for (i, (bad, make, _)) in bad_images(&tmp.0).into_iter().enumerate() {
        let p = dir.join(format!("bad{i}.{}", bad.extension().unwrap().to_string_lossy()));
        make(&p);
        bad_paths.push(p);
    }
    let o = LoadOptions { skip_bad: true, ..opts(8) };
    let ds = load(&dir, &o).unwrap();
    assert_eq!(ds.names, ["good.png"]);
    assert_eq!(ds.skipped.len(), bad_paths.len());
    for p in &bad_paths {
        assert!(ds.skipped.iter().any(|s| &s.path == p && !s.reason.is_empty()), "{} not reported", p.display());
    }
    // All bad: an error, not an empty dataset.
    std::fs::remove_file(dir.join("good.png")).unwrap();
    let e = load(&dir, &o).unwrap_err().to_string();
    assert!(e.contains("every image was skipped"), "{e}");
}

fn write_poses(path: &Path, entries: &[(&str, f64, f64)]) {
    let map: serde_json::Map<String, serde_json::Value> = entries
        .iter()
        .map(|(n, p, y)| (n.to_string(), serde_json::json!({ "phi": p, "theta": y, "radius": 1.0 })))
        .collect();
    std::fs::write(path, serde_json::to_string(&map).unwrap()).unwrap();
}

#[test]
fn camera_param_layout_reads_poses_and_rejects_inconsistencies() {
    let tmp = TempDir::new("load-json").unwrap();
    let d = tmp.path("64_PHOTOSHAPE_CHAIR_1_view");
    std::fs::create_dir_all(&d).unwrap();
    for (n, c) in [("0001.png", [9, 9, 9]), ("0002.png", [99, 99, 99]), ("0003.png", [199, 199, 199])] {
        solid_rgb(&d.join(n), 16, 16, c);
    }
    let poses = d.join(CAMERA_PARAM_FILE);
    write_poses(&poses, &[("0002.png", 1.1, -0.5), ("0001.png", 0.9, 2.0), ("0003.png", 1.3, 3.0)]);
    let ds = load(&d, &LoadOptions { require_poses: true, ..opts(8) }).unwrap();
    assert_eq!(ds.layout, Layout::CameraParam);
    assert_eq!(ds.names, ["0001.png", "0002.png", "0003.png"]);
    let p = Vec::<f32>::try_from(ds.poses.as_ref().unwrap().view([-1])).unwrap();
    assert_eq!(p, [0.9, 2.0, 1.1, -0.5, 1.3, 3.0]);
    assert_all_near(&pixels(&ds, 1), [99, 99, 99], 0, "0002.png");
    assert!(ds.flip.is_none());

    // A pose naming a missing image.
    write_poses(
        &poses,
        &[("0001.png", 0.9, 2.0), ("0002.png", 1.1, -0.5), ("0003.png", 1.3, 3.0), ("0004.png", 1.0, 0.0)],
    );
    let e = load(&d, &opts(8)).unwrap_err().to_string();
    assert!(e.contains("0004.png") && e.contains("missing") && e.contains(CAMERA_PARAM_FILE), "{e}");
    // An image without a pose.
    write_poses(&poses, &[("0001.png", 0.9, 2.0), ("0002.png", 1.1, -0.5)]);
    let e = load(&d, &opts(8)).unwrap_err().to_string();
    assert!(e.contains("0003.png") && e.contains("has no pose"), "{e}");
    // Both skipped with skip_bad, with a count.
    write_poses(&poses, &[("0001.png", 0.9, 2.0), ("0002.png", 1.1, -0.5), ("0004.png", 1.0, 0.0)]);
    let ds = load(&d, &LoadOptions { skip_bad: true, ..opts(8) }).unwrap();
    assert_eq!((ds.len(), ds.skipped.len()), (2, 2));
    // A malformed entry or file names the pose file.
    std::fs::write(&poses, r#"{"0001.png": {"phi": 1.0}}"#).unwrap();
    let e = load(&d, &opts(8)).unwrap_err().to_string();
    assert!(e.contains(&poses.display().to_string()) && e.contains("theta"), "{e}");
    std::fs::write(&poses, "{ not json").unwrap();
    let e = load(&d, &opts(8)).unwrap_err().to_string();
    assert!(e.contains(&poses.display().to_string()) && e.contains("not a pose file"), "{e}");
}

#[test]
fn folders_take_an_optional_pose_file_and_require_poses_when_told() {
    let tmp = TempDir::new("load-folder-poses").unwrap();
    let d = tmp.path("imgs");
    std::fs::create_dir_all(&d).unwrap();
    solid_rgb(&d.join("a.png"), 8, 8, [1, 1, 1]);
    solid_rgb(&d.join("b.png"), 8, 8, [2, 2, 2]);
    let e = load(&d, &LoadOptions { require_poses: true, ..opts(8) }).unwrap_err().to_string();
    assert!(e.contains(&d.display().to_string()) && e.contains("poses are required"), "{e}");
    let pose_file = tmp.path("poses.json");
    write_poses(&pose_file, &[("a.png", 1.0, 0.5), ("b.png", 1.2, -0.5)]);
    let o = LoadOptions { poses: Some(pose_file.clone()), require_poses: true, ..opts(8) };
    let ds = load(&d, &o).unwrap();
    assert_eq!(Vec::<f32>::try_from(ds.poses.unwrap().view([-1])).unwrap(), [1.0, 0.5, 1.2, -0.5]);
    write_poses(&pose_file, &[("a.png", 1.0, 0.5)]);
    let e = load(&d, &o).unwrap_err().to_string();
    assert!(e.contains("b.png") && e.contains("has no pose"), "{e}");
}

fn c2w_at(x: f64, y: f64, z: f64) -> [[f64; 4]; 4] {
    [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]]
}

#[test]
fn carla_layout_converts_extrinsics_and_flips_with_the_release_rule() {
    let tmp = TempDir::new("load-carla").unwrap();
    let imgs = tmp.path("carla/carla32");
    let poses = tmp.path("carla/carla_poses");
    std::fs::create_dir_all(&imgs).unwrap();
    std::fs::create_dir_all(&poses).unwrap();
    // An asymmetric image: left half black, right half white.
    let img = ImageBuffer::from_fn(8, 8, |x, _| Rgb(if x < 4 { [0u8, 0, 0] } else { [255, 255, 255] }));
    let positions = [(0.3, -0.8, 0.5), (-0.6, 0.2, 0.7)];
    for (i, &(x, y, z)) in positions.iter().enumerate() {
        img.save(imgs.join(format!("{i:04}.png"))).unwrap();
        std::fs::write(poses.join(format!("{i:04}_extrinsics.npy")), npy::encode_matrix_f64(&c2w_at(x, y, z))).unwrap();
    }
    let ds = load(&imgs, &LoadOptions { require_poses: true, ..opts(8) }).unwrap();
    assert_eq!(ds.layout, Layout::Carla);
    assert_eq!(ds.flip.unwrap().probability, 0.5);
    let got = Vec::<f32>::try_from(ds.poses.as_ref().unwrap().view([-1])).unwrap();
    for (i, &(x, y, z)) in positions.iter().enumerate() {
        let m = c2w_at(x, y, z);
        let want = carla_pose(&[m[0], m[1], m[2]]).unwrap();
        // The release's formula, written out: rows permuted to (y, z, x).
        let (p0, p1, p2) = (y, z, x);
        let theta = (-p0).atan2(p2) + std::f64::consts::FRAC_PI_2;
        let phi = (-p1 / (p0 * p0 + p2 * p2).sqrt()).atan() + std::f64::consts::FRAC_PI_2;
        assert_eq!(want, [phi, theta]);
        assert_eq!([got[2 * i], got[2 * i + 1]], [phi as f32, theta as f32]);
    }
    // A flipped batch mirrors the image and maps θ → π − θ; unflipped entries are untouched.
    let (batch, bp) = ds.batch(&[0, 1], Some(&[true, false])).unwrap();
    let bp = Vec::<f32>::try_from(bp.unwrap().view([-1])).unwrap();
    assert!((bp[1] - (std::f32::consts::PI - got[1])).abs() < 1e-6 && bp[0] == got[0]);
    assert_eq!([bp[2], bp[3]], [got[2], got[3]]);
    let row = |t: &Tensor| Vec::<f32>::try_from(t.get(0).get(0).contiguous()).unwrap(); // channel 0, top row
    assert_eq!(row(&batch.get(0)), [1.0, 1.0, 1.0, 1.0, -1.0, -1.0, -1.0, -1.0]);
    assert_eq!(row(&batch.get(1)), [-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0]);
    assert!(ds.batch(&[2], None).is_err());

    // A missing pose names the image; a corrupt one names the .npy; skip_bad skips both.
    img.save(imgs.join("0002.png")).unwrap();
    let e = load(&imgs, &opts(8)).unwrap_err().to_string();
    assert!(e.contains("0002.png") && e.contains("has no pose"), "{e}");
    std::fs::write(poses.join("0002_extrinsics.npy"), b"\x93NUMPY garbage").unwrap();
    let e = load(&imgs, &opts(8)).unwrap_err().to_string();
    assert!(e.contains("0002_extrinsics.npy"), "{e}");
    let ds = load(&imgs, &LoadOptions { skip_bad: true, ..opts(8) }).unwrap();
    assert_eq!((ds.len(), ds.skipped.len()), (2, 1));
}

#[test]
fn the_cache_is_reused_rebuilt_when_files_change_and_survives_corruption() {
    let tmp = TempDir::new("load-cache").unwrap();
    let d = tmp.path("imgs");
    std::fs::create_dir_all(&d).unwrap();
    for i in 0..5u8 {
        solid_rgb(&d.join(format!("{i}.png")), 20, 20, [i * 40, 7, 9]);
    }
    let o = LoadOptions { cache: true, ..opts(8) };
    let first = load(&d, &o).unwrap();
    let CacheStatus::Decoded(Some(cache)) = &first.cache else { panic!("{:?}", first.cache) };
    assert!(cache.is_file() && cache.starts_with(&d));
    let second = load(&d, &o).unwrap();
    assert_eq!(second.cache, CacheStatus::Hit(cache.clone()));
    assert!(second.pixels.equal(&first.pixels));
    assert_eq!(second.names, first.names);
    // Another resolution has its own cache.
    assert!(matches!(
        load(&d, &LoadOptions { resolution: 4, ..o.clone() }).unwrap().cache,
        CacheStatus::Decoded(Some(_))
    ));
    // A changed image invalidates the cache.
    solid_rgb(&d.join("2.png"), 24, 24, [250, 250, 250]);
    let third = load(&d, &o).unwrap();
    assert!(matches!(third.cache, CacheStatus::Decoded(Some(_))));
    assert_all_near(&pixels(&third, 2), [250, 250, 250], 0, "changed image");
    // A truncated cache file is rebuilt, not trusted.
    let bytes = std::fs::read(cache).unwrap();
    std::fs::write(cache, &bytes[..bytes.len() / 2]).unwrap();
    let fourth = load(&d, &o).unwrap();
    assert!(matches!(fourth.cache, CacheStatus::Decoded(Some(_))));
    assert!(fourth.pixels.equal(&third.pixels));
    // An unwritable cache location is reported, and loading still succeeds.
    let blocker = tmp.path("blocker");
    std::fs::write(&blocker, b"a file, not a folder").unwrap();
    let ds = load(&d, &LoadOptions { cache_dir: Some(blocker.join("cache")), ..o }).unwrap();
    assert!(matches!(ds.cache, CacheStatus::WriteFailed(..)), "{:?}", ds.cache);
}

#[test]
fn missing_or_empty_folders_are_errors() {
    let tmp = TempDir::new("load-empty").unwrap();
    let e = load(&tmp.path("nope"), &opts(8)).unwrap_err().to_string();
    assert!(e.contains("nope") && e.contains("not a folder"), "{e}");
    let e = load(&tmp.0, &opts(8)).unwrap_err().to_string();
    assert!(e.contains("no images found"), "{e}");
}

#[test]
fn alpha_is_kept_area_resized_cached_and_mirrored_with_its_image() {
    let tmp = TempDir::new("load-alpha").unwrap();
    let d = tmp.path("imgs");
    std::fs::create_dir_all(&d).unwrap();
    // 4 × 4: the left half opaque red, the right half transparent (its colour must not show).
    let img = ImageBuffer::from_fn(4, 4, |x, _| if x < 2 { Rgba([255u8, 0, 0, 255]) } else { Rgba([0, 0, 255, 0]) });
    img.save(d.join("a.png")).unwrap();
    // Half transparent everywhere.
    ImageBuffer::from_pixel(4, 4, Rgba([0u8, 0, 0, 102])).save(d.join("b.png")).unwrap();
    let o = LoadOptions { cache: true, ..opts(2) };
    let ds = load(&d, &o).unwrap();
    let alpha = ds.alpha.as_ref().expect("alpha is kept where a pixel is transparent");
    assert_eq!(alpha.size(), [2, 1, 2, 2]);
    // Each 2 × 2 output pixel is the mean of a 2 × 2 block: exact values, 255·0.4 = 102.
    assert_eq!(Vec::<u8>::try_from(alpha.view([-1])).unwrap(), [255, 0, 255, 0, 102, 102, 102, 102]);
    assert_eq!(pixels(&ds, 0), [255, 0, 0, 255, 255, 255, 255, 0, 0, 255, 255, 255]);
    // The cache holds it too.
    let again = load(&d, &o).unwrap();
    assert!(matches!(again.cache, CacheStatus::Hit(_)), "{:?}", again.cache);
    assert!(again.alpha.as_ref().unwrap().equal(alpha));
    // A mirrored image comes with its mirrored alpha, in [0, 1].
    let a = ds.alpha_batch(&[0, 0], Some(&[false, true])).unwrap();
    let want = Tensor::from_slice(&[1.0f32, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0]).view([2, 1, 2, 2]);
    assert!(a.equal(&want), "{a}");
    // Opaque images have none.
    let opaque = tmp.path("opaque");
    std::fs::create_dir_all(&opaque).unwrap();
    solid_rgb(&opaque.join("a.png"), 4, 4, [1, 2, 3]);
    ImageBuffer::from_pixel(4, 4, Rgba([9u8, 9, 9, 255])).save(opaque.join("b.png")).unwrap();
    let ds = load(&opaque, &o).unwrap();
    assert!(ds.alpha.is_none() && ds.alpha_batch(&[0], None).is_none());
}
