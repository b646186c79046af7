//! The procedural dataset: determinism, metadata round-trip, the pose convention (the
//! generator's camera agrees with gdrf_core::camera at the recorded poses), the swap
//! renderer, topology (holes where the parameters say), fit inside the camera, the
//! split, and generation on first use from a data config.
mod common;

use common::TempDir;
use gdrf_core::camera::{cam2world_rotation, camera_origins, Poses};
use gdrf_core::config::CameraConfig;
use gdrf_core::data::synth::chairs::{Arms, Back, ChairParams, Legs, SeatShape, BACK};
use gdrf_core::data::synth::material::{Appearance, PARTS};
use gdrf_core::data::synth::render::{fit_radius, render, Geometry, RenderOptions, Rendered, Scene};
use gdrf_core::data::synth::rng::{Rng, Stream};
use gdrf_core::data::synth::sdf::{v3, Prim, Rot, Shape, V3};
use gdrf_core::data::synth::{self, Category, ShapeParams, SynthOptions};
use gdrf_core::data::{self, DataConfig, LoadOptions, Metadata, Prepared, Split};
use std::path::Path;
use tch::{Device, Kind, Tensor};

fn small(category: Category, count: usize) -> SynthOptions {
    SynthOptions { category, count, resolution: 32, supersample: 2, seed: 5, ..Default::default() }
}

fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir.join("images"))
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap())
        })
        .collect();
    v.sort();
    v
}

#[test]
fn same_seed_gives_byte_identical_datasets_for_any_thread_count() {
    let tmp = TempDir::new("synth-determinism").unwrap();
    for category in Category::ALL {
        let opts = small(category, 10);
        let (a, b, c) = (tmp.path("a"), tmp.path("b"), tmp.path("c"));
        synth::generate(&a, &opts, 1, &|_| {}).unwrap();
        synth::generate(&b, &opts, 3, &|_| {}).unwrap();
        assert_eq!(files(&a), files(&b), "{category:?}: images differ between 1 and 3 threads");
        for f in [data::METADATA_FILE, "camera_param.json"] {
            assert_eq!(std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap(), "{f}");
        }
        synth::generate(&c, &SynthOptions { seed: 6, ..opts }, 2, &|_| {}).unwrap();
        let (fa, fc) = (files(&a), files(&c));
        assert!(fa.iter().zip(&fc).all(|(x, y)| x.1 != y.1), "another seed must give other images");
        for d in [a, b, c] {
            std::fs::remove_dir_all(d).unwrap();
        }
    }
}

#[test]
fn metadata_round_trips_and_regenerates_each_image() {
    let tmp = TempDir::new("synth-meta").unwrap();
    let dir = tmp.path("d");
    let opts = SynthOptions { views_per_object: 2, ..small(Category::Chairs, 8) };
    let written = synth::generate(&dir, &opts, 2, &|_| {}).unwrap();
    let read = Metadata::load(&dir).unwrap();
    assert_eq!(written, read);
    assert_eq!(read.part_names, ["seat", "back", "legs", "arms"]);
    assert_eq!(read.images.len(), 8);
    // Each record is exactly what the options and index determine.
    for (i, r) in read.images.iter().enumerate() {
        assert_eq!(r, &synth::image_record(&opts, i));
        assert_eq!((r.object, r.view), (i / 2, i % 2));
    }
    // Both views of an object share shape, appearance and seed but not the pose.
    let (v0, v1) = (&read.images[2], &read.images[3]);
    assert_eq!((&v0.shape, &v0.appearance, v0.seed), (&v1.shape, &v1.appearance, v1.seed));
    assert_ne!((v0.pitch, v0.yaw), (v1.pitch, v1.yaw));
    // camera_param.json (the authors' format) carries the same poses.
    let poses = data::layouts::read_camera_param(&dir.join("camera_param.json")).unwrap();
    for r in &read.images {
        assert_eq!(poses[&r.file], [r.pitch, r.yaw]);
    }
    // Re-rendering from the metadata alone reproduces the PNG bytes.
    for r in &read.images[..3] {
        let img = synth::render_object(&r.shape, &r.appearance, r.pitch, r.yaw, &read.options).unwrap();
        let png = synth::encode_png(img.to_rgba8(), 32).unwrap();
        assert_eq!(png, std::fs::read(dir.join(&r.file)).unwrap(), "{}", r.file);
    }
    // Poses come from the configured distribution (chairs: uniform yaw, pitch range).
    let cam = CameraConfig::chair();
    for r in &read.images {
        assert!((cam.v_mean - cam.v_std..=cam.v_mean + cam.v_std).contains(&r.pitch), "{}", r.pitch);
        assert!((-std::f64::consts::PI..=std::f64::consts::PI).contains(&r.yaw));
    }
}

/// Pixel (column, row) of a world point seen from (pitch, yaw), computed with
/// gdrf_core::camera's rotation and origin (not the generator's camera).
fn project(p: V3, pitch: f64, yaw: f64, res: usize, fov_deg: f64) -> (f64, f64) {
    let poses = Poses::from_angles(&[(pitch, yaw)], Kind::Double, Device::Cpu);
    let r = cam2world_rotation(&poses).get(0);
    let o = camera_origins(&poses, 1.0).get(0);
    let d = Tensor::from_slice(&[p.x as f64, p.y as f64, p.z as f64]) - o;
    let cam = Vec::<f64>::try_from(r.transpose(0, 1).matmul(&d)).unwrap(); // world → camera
    let t = (fov_deg.to_radians() / 2.0).tan();
    let (x, y) = (cam[0] / -cam[2] / t, cam[1] / -cam[2] / t);
    let m = (res - 1) as f64 / 2.0;
    ((x + 1.0) * m, (1.0 - y) * m)
}

fn centroid(weights: impl Iterator<Item = f32>, res: usize) -> (f64, f64, f64) {
    let (mut m, mut cx, mut cy) = (0.0, 0.0, 0.0);
    for (i, w) in weights.enumerate() {
        let w = w as f64;
        m += w;
        cx += w * (i % res) as f64;
        cy += w * (i / res) as f64;
    }
    (m, cx / m, cy / m)
}

fn alpha_of_png(path: &Path) -> Vec<f32> {
    let img = image::open(path).unwrap().into_rgba8();
    img.pixels().map(|p| p.0[3] as f32 / 255.0).collect()
}

#[test]
fn recorded_poses_follow_the_camera_convention() {
    let tmp = TempDir::new("synth-pose").unwrap();
    let dir = tmp.path("d");
    let opts = SynthOptions { resolution: 64, ..small(Category::Chairs, 12) };
    let meta = synth::generate(&dir, &opts, 2, &|_| {}).unwrap();
    let radius = fit_radius(&opts.camera);
    let ro = RenderOptions { resolution: 64, supersample: 2, fov_deg: 50.0, shadows: false };
    for r in &meta.images {
        // 1. A marker sphere off the centre, rendered by the generator's renderer at the
        //    recorded pose, lands where gdrf_core::camera projects it.
        let marker = v3(0.12, -0.08, 0.15);
        let geo = Geometry {
            prims: vec![Prim::new(Shape::Sphere { radius: 0.03 }, Rot::IDENTITY, marker, 0)],
            frames: [(Rot::IDENTITY, V3::default()); PARTS],
        };
        let scene = Scene::with_transform(&geo, &r.appearance, V3::default(), 1.0);
        let img = render(&scene, r.pitch, r.yaw, &ro).unwrap();
        let (m, cx, cy) = centroid(img.alpha.iter().copied(), 64);
        let (px, py) = project(marker, r.pitch, r.yaw, 64, 50.0);
        assert!(
            m > 3.0 && (cx - px).abs() < 0.5 && (cy - py).abs() < 0.5,
            "{}: marker at ({cx:.1}, {cy:.1}), projected ({px:.1}, {py:.1})",
            r.file
        );

        // 2. The object's centre (the origin after fitting) projects to the middle of the
        //    image and the alpha mass in the PNG is around it.
        let (px, py) = project(V3::default(), r.pitch, r.yaw, 64, 50.0);
        assert!((px - 31.5).abs() < 1e-9 && (py - 31.5).abs() < 1e-9);
        let (m, cx, cy) = centroid(alpha_of_png(&dir.join(&r.file)).into_iter(), 64);
        assert!(
            m > 50.0 && (cx - px).abs() < 9.0 && (cy - py).abs() < 9.0,
            "{}: alpha centroid ({cx:.1}, {cy:.1})",
            r.file
        );

        // 3. Each part shows up around the projection of its primitives' centre.
        let scene = Scene::new(&r.shape.geometry(), &r.appearance, radius).unwrap();
        let img = render(&scene, r.pitch, r.yaw, &ro).unwrap();
        for part in 0..PARTS {
            let prims: Vec<&Prim> = scene.prims().iter().filter(|p| p.part as usize == part).collect();
            let (m, cx, cy) = centroid((0..64 * 64).map(|i| img.parts[i * PARTS + part]), 64);
            if prims.len() < 2 || m < 30.0 {
                continue; // small or hidden parts: the centroid says little
            }
            let c = prims.iter().fold(V3::default(), |a, p| a + p.pos) * (1.0 / prims.len() as f32);
            let (px, py) = project(c, r.pitch, r.yaw, 64, 50.0);
            assert!(
                (cx - px).abs() < 8.0 && (cy - py).abs() < 8.0,
                "{} part {part}: seen at ({cx:.1}, {cy:.1}), projected ({px:.1}, {py:.1})",
                r.file
            );
        }
    }
}

#[test]
fn swaps_keep_the_shape_and_change_the_appearance() {
    let tmp = TempDir::new("synth-swap").unwrap();
    let dir = tmp.path("d");
    let meta = synth::generate(&dir, &small(Category::Chairs, 6), 2, &|_| {}).unwrap();
    // Shape i with appearance i is image i, byte for byte.
    for i in [0, 4] {
        let own = synth::render_swap(&meta, i, i, None, None, None).unwrap();
        let png = synth::encode_png(own.to_rgba8(), 32).unwrap();
        assert_eq!(png, std::fs::read(dir.join(&meta.images[i].file)).unwrap());
    }
    // Shape 1 with appearance 2: object 1's silhouette, exactly, with other colours.
    let own = synth::render_swap(&meta, 1, 1, None, None, None).unwrap();
    let swapped = synth::render_swap(&meta, 1, 2, None, None, None).unwrap();
    assert_eq!(own.alpha, swapped.alpha);
    assert_eq!(own.parts, swapped.parts);
    let diff: f32 = own.rgb.iter().zip(&swapped.rgb).map(|(a, b)| (a - b).abs()).sum();
    assert!(diff > 10.0, "appearance swap changed almost nothing ({diff})");
    // The other way round: object 2's silhouette.
    let other = synth::render_swap(&meta, 2, 1, None, None, None).unwrap();
    assert_ne!(other.alpha, own.alpha);
    // Any pose and resolution.
    let posed = synth::render_swap(&meta, 1, 2, Some((0.9, 2.0)), Some(48), Some(1)).unwrap();
    assert_eq!(posed.alpha.len(), 48 * 48);
    assert!(synth::render_swap(&meta, 99, 0, None, None, None).unwrap_err().to_string().contains("object 99"));
}

fn chair() -> ChairParams {
    ChairParams {
        seat: SeatShape::Square,
        seat_width: 0.48,
        seat_depth: 0.45,
        seat_height: 0.45,
        seat_thickness: 0.05,
        member: 0.035,
        legs: Legs::Four { splay: 0.0, round: false, stretchers: false },
        back: Back::Solid,
        back_height: 0.45,
        back_tilt: 0.0,
        arms: Arms::None,
        arm_height: 0.2,
    }
}

fn appearance() -> Appearance {
    Appearance::sample(&mut Rng::new(3, Stream::Appearance))
}

/// Renders chairs in the frame fitted to `reference` (so that pixels compare), from the
/// front (yaw π/2 puts the camera on +z) and slightly above.
fn front_view(c: &ChairParams, reference: &ChairParams, res: usize) -> (Rendered, Scene) {
    let (centre, scale) = Scene::fit(&reference.geometry(), fit_radius(&CameraConfig::chair())).unwrap();
    let scene = Scene::with_transform(&c.geometry(), &appearance(), centre, scale);
    let ro = RenderOptions { resolution: res, supersample: 2, fov_deg: 50.0, shadows: false };
    (render(&scene, 1.3, std::f64::consts::FRAC_PI_2, &ro).unwrap(), scene)
}

/// Pixel of a chair-natural point in `front_view`'s frame.
fn front_pixel(scene: &Scene, natural: V3, res: usize) -> (usize, usize) {
    let (x, y) = project(scene.to_world(natural), 1.3, std::f64::consts::FRAC_PI_2, res, 50.0);
    (x.round() as usize, y.round() as usize)
}

#[test]
fn a_stool_differs_from_a_chair_only_where_the_back_is() {
    let res = 96;
    let with_back = chair();
    let stool = ChairParams { back: Back::None, ..chair() };
    let (a, scene) = front_view(&with_back, &with_back, res);
    let (b, _) = front_view(&stool, &with_back, res);
    // The back's image region: rows above the seat's top at the back edge.
    let (_, seat_row) = front_pixel(&scene, v3(0.0, 0.45, -0.2), res);
    let (mut above, mut below) = (0.0, 0.0);
    for row in 0..res {
        for col in 0..res {
            let d = (a.alpha[row * res + col] - b.alpha[row * res + col]).abs();
            // A band of rows around the seat's back edge is left out (antialiased edge).
            if row + 1 < seat_row {
                above += d
            } else if row > seat_row + 1 {
                below += d
            }
        }
    }
    assert!(above > 100.0, "the back should add coverage above the seat ({above})");
    assert!(below < 0.02 * above, "chair and stool should agree below the seat ({below} vs {above})");
    // Where the back's centre projects, the chair is covered by its back part, the stool is empty.
    let (col, row) = front_pixel(&scene, v3(0.0, 0.45 + 0.225, -0.2), res);
    let i = row * res + col;
    assert!(a.parts[i * PARTS + BACK as usize] > 0.99 && b.alpha[i] == 0.0);
}

#[test]
fn slatted_ladder_and_frame_backs_have_holes() {
    let res = 128;
    let back_row = |c: &ChairParams, y: f32| {
        let (img, scene) = front_view(c, c, res);
        let (_, row) = front_pixel(&scene, v3(0.0, 0.45 + y, -0.2), res);
        let (left, _) = front_pixel(&scene, v3(-0.3, 0.45 + y, -0.2), res);
        let (right, _) = front_pixel(&scene, v3(0.3, 0.45 + y, -0.2), res);
        (img, scene, row, left, right)
    };
    // Count covered runs along a row (alpha > 0.5), with background between them.
    let runs =
        |alpha: &[f32]| alpha.windows(2).filter(|w| w[0] <= 0.5 && w[1] > 0.5).count() + usize::from(alpha[0] > 0.5);
    for count in 2..=6 {
        let c = ChairParams { back: Back::Slats { count }, ..chair() };
        let (img, _, row, left, right) = back_row(&c, 0.2);
        let line = &img.alpha[row * res + left..row * res + right];
        assert_eq!(runs(line), count as usize + 2, "{count} slats + 2 posts expected along {line:?}");
        assert!(line.iter().filter(|&&a| a == 0.0).count() > count as usize, "background between slats");
    }
    // A solid back covers the same row in one piece.
    let (img, _, row, left, right) = back_row(&chair(), 0.2);
    assert_eq!(runs(&img.alpha[row * res + left..row * res + right]), 1);
    // Ladder: rungs with background between them along the back's centre column.
    for rungs in 2..=4 {
        let c = ChairParams { back: Back::Ladder { rungs }, ..chair() };
        let (img, scene, ..) = back_row(&c, 0.0);
        let (col, top) = front_pixel(&scene, v3(0.0, 0.45 + 0.46, -0.2), res);
        let (_, bottom) = front_pixel(&scene, v3(0.0, 0.5, -0.2), res);
        let column: Vec<f32> = (top..bottom).map(|r| img.alpha[r * res + col]).collect();
        assert_eq!(runs(&column), rungs as usize, "{rungs} rungs expected along {column:?}");
    }
    // Frame: an opening in the middle, rails above and below it.
    let c = ChairParams { back: Back::Frame { rail: 0.07 }, ..chair() };
    let (img, scene, ..) = back_row(&c, 0.0);
    let at = |y: f32| {
        let (col, row) = front_pixel(&scene, v3(0.0, 0.45 + y, -0.2), res);
        img.alpha[row * res + col]
    };
    assert_eq!(at(0.25), 0.0, "the frame's opening shows the background");
    assert!(at(0.45 - 0.035) > 0.99 && at(0.15 * 0.45 + 0.035) > 0.99, "top and bottom rails");
}

#[test]
fn every_object_fits_the_camera_at_every_pose() {
    let cam = CameraConfig::chair();
    let radius = fit_radius(&cam);
    assert!(radius <= 0.4 && radius > 0.3);
    let ro = RenderOptions { resolution: 32, supersample: 1, fov_deg: cam.fov_deg, shadows: false };
    let extremes = [cam.v_mean - cam.v_std, cam.v_mean + cam.v_std];
    for category in Category::ALL {
        for i in 0..40u64 {
            let (shape, app) = synth::sample_object(category, i);
            let scene = Scene::new(&shape.geometry(), &app, radius).unwrap();
            // Inside the ray range [0.6, 1.4] from every camera on the unit sphere.
            for p in scene.prims() {
                let (lo, hi) = p.aabb();
                for k in 0..8 {
                    let pick = |bit: usize, a: f32, b: f32| if k >> bit & 1 == 1 { b } else { a };
                    let corner = v3(pick(0, lo.x, hi.x), pick(1, lo.y, hi.y), pick(2, lo.z, hi.z));
                    assert!(corner.length() <= radius as f32 * 1.001, "{category:?} {i}: {corner:?}");
                }
            }
            // Never touching the image border.
            for pitch in extremes {
                for k in 0..6 {
                    let yaw = -std::f64::consts::PI + k as f64 * 1.1;
                    let img = render(&scene, pitch, yaw, &ro).unwrap();
                    let border = (0..32).flat_map(|j| [j, 31 * 32 + j, j * 32, j * 32 + 31]);
                    assert!(border.map(|b| img.alpha[b]).all(|a| a == 0.0), "{category:?} {i} at ({pitch}, {yaw})");
                    assert!(img.alpha.iter().sum::<f32>() > 20.0);
                }
            }
        }
    }
}

#[test]
fn chairs_cover_every_topology_and_appearance_is_independent_of_shape() {
    let (mut legs, mut backs, mut arms) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..300u64 {
        let (ShapeParams::Chair(c), _) = synth::sample_object(Category::Chairs, i) else { panic!("not a chair") };
        let name = |s: String| s.split([' ', '{', '(']).next().unwrap().to_string();
        legs.push(name(format!("{:?}", c.legs)));
        backs.push(name(format!("{:?}", c.back)));
        arms.push(format!("{:?}", c.arms));
        if matches!(c.back, Back::None) || c.seat == SeatShape::Round {
            assert_eq!(c.arms, Arms::None, "arms need a back and a square seat");
        }
    }
    for (kinds, want) in [(&mut legs, 5), (&mut backs, 5), (&mut arms, 3)] {
        kinds.sort();
        kinds.dedup();
        assert_eq!(kinds.len(), want, "{kinds:?}");
    }
    // Shape and appearance come from separate streams: the appearance of object i is
    // that of the appearance stream alone, whatever the category.
    let seed = synth::rng::object_seed(0, 3);
    let (_, a_chair) = synth::sample_object(Category::Chairs, seed);
    let (_, a_table) = synth::sample_object(Category::Tables, seed);
    assert_eq!(a_chair, a_table);
    assert_eq!(a_chair, Appearance::sample(&mut Rng::new(seed, Stream::Appearance)));
}

#[test]
fn the_split_never_shares_an_object() {
    let opts = SynthOptions { views_per_object: 3, held_out_fraction: 0.3, ..small(Category::Tables, 600) };
    let records: Vec<_> = (0..opts.count).map(|i| synth::image_record(&opts, i)).collect();
    for obj in records.chunks(3) {
        assert!(obj.iter().all(|r| r.split == obj[0].split && r.object == obj[0].object));
    }
    let held = records.iter().filter(|r| r.split == Split::HeldOut).count() as f64 / 600.0;
    assert!((0.2..0.4).contains(&held), "{held}");
}

#[test]
fn a_data_config_generates_on_first_use_and_loads_the_train_split() {
    let tmp = TempDir::new("synth-config").unwrap();
    let toml_text = format!(
        r#"
        path = "{}"
        [synth]
        category = "tables"
        count = 12
        resolution = 32
        supersample = 1
        seed = 9
        "#,
        tmp.path("tables").display()
    );
    let cfg: DataConfig = toml::from_str(&toml_text).unwrap();
    assert_eq!(cfg.prepare(2, &|_| {}).unwrap(), Prepared::Generated);
    assert_eq!(cfg.prepare(2, &|_| {}).unwrap(), Prepared::Existing);
    let ds = data::load(&cfg.path, &cfg.load_options(16, 2), &|_| {}).unwrap();
    let meta = Metadata::load(&cfg.path).unwrap();
    let train: Vec<_> = meta.images.iter().filter(|r| r.split == Split::Train).collect();
    assert_eq!(ds.len(), train.len());
    assert_eq!(ds.names, train.iter().map(|r| r.file.clone()).collect::<Vec<_>>());
    let poses = Vec::<f32>::try_from(ds.poses.as_ref().unwrap().view([-1])).unwrap();
    assert_eq!(poses[0], train[0].pitch as f32);
    assert_eq!(poses[1], train[0].yaw as f32);
    assert_eq!(ds.images().size(), [train.len() as i64, 3, 16, 16]);
    // Other options on disk are an error naming what differs, never a silent overwrite.
    let mut other = cfg.clone();
    other.synth.as_mut().unwrap().count = 13;
    let e = other.prepare(2, &|_| {}).unwrap_err().to_string();
    assert!(e.contains("count: 12 on disk vs 13 wanted"), "{e}");
    let held = LoadOptions { split: Some(Split::HeldOut), ..cfg.load_options(16, 2) };
    match data::load(&cfg.path, &held, &|_| {}) {
        Ok(h) => assert_eq!(h.len() + ds.len(), 12),
        Err(e) => assert!(e.to_string().contains("no images"), "{e}"),
    }
}

#[test]
fn regenerating_a_folder_leaves_exactly_the_new_dataset() {
    let tmp = TempDir::new("synth-regen").unwrap();
    let dir = tmp.path("d");
    synth::generate(&dir, &small(Category::Chairs, 6), 2, &|_| {}).unwrap();
    let meta = synth::generate(&dir, &SynthOptions { seed: 1, ..small(Category::Tables, 3) }, 2, &|_| {}).unwrap();
    let names: Vec<String> = files(&dir).into_iter().map(|f| format!("images/{}", f.0)).collect();
    assert_eq!(names, meta.images.iter().map(|r| r.file.clone()).collect::<Vec<_>>());
    assert_eq!(Metadata::load(&dir).unwrap().options.category, Category::Tables);
}
