//! End-to-end tests of the `mrfmap` binary: the happy path on a small simulated scene and
//! every kind of bad input the README promises a clear error for.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SCENE: &str = r#"
[camera]
fx = 60.0
fy = 60.0
cx = 39.5
cy = 29.5
width = 80
height = 60
depth_scale = 5000.0
min_depth = 0.2
max_depth = 6.0
[noise]
bias = [0.0, 0.0, 0.002]
std = [0.002, 0.0, 0.002]
[[box]]
min = [-2.0, -2.0, -0.1]
max = [2.0, 2.0, 0.0]
[[box]]
min = [-0.3, -0.3, 0.0]
max = [0.3, 0.3, 0.6]
[[sphere]]
center = [0.8, 0.0, 0.3]
radius = 0.3
[orbit]
center = [0.0, 0.0, 0.3]
radius = 2.0
height = 1.2
views = 4
"#;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mrfmap"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A fresh folder per test, removed when the test ends (kept, and its path printed, when
/// `MRFMAP_KEEP_TEST_DIRS` is set, to look at what a failing test wrote).
struct Workdir(tempfile::TempDir);

impl std::ops::Deref for Workdir {
    type Target = Path;

    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for Workdir {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}

impl Drop for Workdir {
    fn drop(&mut self) {
        if std::env::var_os("MRFMAP_KEEP_TEST_DIRS").is_some() {
            eprintln!("kept {}", self.0.path().display());
            self.0.disable_cleanup(true);
        }
    }
}

fn workdir(name: &str) -> Workdir {
    Workdir(tempfile::Builder::new().prefix(&format!("mrfmap-cli-{name}-")).tempdir().unwrap())
}

/// Writes the scene and simulates it into `dir/data`.
fn dataset(dir: &Path) -> PathBuf {
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let data = dir.join("data");
    let o = run(&["simulate", scene.to_str().unwrap(), data.to_str().unwrap(), "--seed", "3"]);
    assert!(o.status.success(), "{}", stderr(&o));
    data
}

/// Simulates the scene into `dir/data` and builds `dir/m.mrfmap` from it (log-odds, 0.05 m).
fn logodds_map(dir: &Path) -> PathBuf {
    let data = dataset(dir);
    let map = dir.join("m.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.05", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    map
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `build` and asserts it fails with a message containing every `needle`, leaving no map.
fn build_fails(data: &Path, extra: &[&str], needles: &[&str]) {
    let out = data.parent().unwrap().join("fail.mrfmap");
    let mut args = vec!["build", s(data), "-o", s(&out), "--resolution", "0.05"];
    args.extend_from_slice(extra);
    let o = run(&args);
    let err = stderr(&o);
    assert!(!o.status.success(), "expected failure for {args:?}");
    for n in needles {
        assert!(err.contains(n), "error {err:?} should mention {n:?}");
    }
    assert!(!err.contains("panicked"), "{err}");
    assert!(!out.exists(), "a failed build must not leave a map");
}

#[test]
fn simulate_build_info_export() {
    let dir = workdir("happy");
    let data = dataset(&dir);
    for f in ["depth/000003.png", "gt_depth/000000.png", "depth.txt", "groundtruth.txt", "camera.toml", "noise.toml"] {
        assert!(data.join(f).is_file(), "{f} missing");
    }
    let map = dir.join("m.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.05", "--exclude", "1", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("3 frames"), "{}", stdout(&o));
    let o = run(&["info", s(&map)]);
    let info = stdout(&o);
    assert!(o.status.success() && info.contains("logodds") && info.contains("0.05 m"), "{info}");
    // The same for scripts: one JSON object with the map's own numbers.
    let o = run(&["info", s(&map), "--json"]);
    let json: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    let loaded = mrfmap::map::Map::load(&map).unwrap();
    assert_eq!(json["voxels"].as_u64().unwrap() as usize, loaded.voxels.len());
    assert_eq!(json["occupied"].as_u64().unwrap() as usize, loaded.occupied_count());
    assert_eq!((json["engine"].as_str(), json["resolution"].as_f64()), (Some("logodds"), Some(0.05)));
    let per_voxel = json["bytes_per_voxel"].as_f64().unwrap();
    assert!(per_voxel > 1.0 && per_voxel < 200.0, "{json}");
    assert_eq!(json["bounds"].as_array().unwrap().len(), 2);
    let ply = dir.join("m.ply");
    let o = run(&["export", s(&map), "--ply", s(&ply), "--occupied-only"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v = mrfmap::outputs::read_ply(&ply).unwrap();
    assert_eq!(v.resolution, Some(0.05));
    let occ = v.column("occupancy").unwrap();
    assert!(v.rows.len() > 100 && v.rows.iter().all(|r| r[occ] > 0.5));
    let loaded = mrfmap::map::Map::load(&map).unwrap();
    assert_eq!(loaded.occupied_count(), v.rows.len());

    // Same seed, same data; the scene's box is mapped as occupied.
    let again = dir.join("again");
    let o = run(&["simulate", s(&dir.join("scene.toml")), s(&again), "--seed", "3"]);
    assert!(o.status.success());
    assert_eq!(
        std::fs::read(data.join("depth/000002.png")).unwrap(),
        std::fs::read(again.join("depth/000002.png")).unwrap()
    );
    // View 2 looks at the box's -x face (x = -0.3) head-on: a voxel there is occupied.
    let face = [-0.32, -0.29, -0.26].iter().filter_map(|x| loaded.occupancy_at([*x, 0.02, 0.3])).fold(0.0f32, f32::max);
    assert!(face > 0.5, "box face occupancy {face}");
    assert!(loaded.occupancy_at([-0.6, 0.02, 0.3]).is_some_and(|p| p < 0.5), "free space in front of the face");

    // The MRF engine through the CLI, with automatic keyframe selection.
    let mrf = dir.join("mrf.mrfmap");
    let o = run(&[
        "build",
        s(&data),
        "-o",
        s(&mrf),
        "--resolution",
        "0.05",
        "--engine",
        "mrf",
        "--keyframes",
        "auto",
        "-q",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&["info", s(&mrf)]);
    assert!(stdout(&o).contains("engine:      mrf") && stdout(&o).contains("keyframes = 4"), "{}", stdout(&o));

    // The CRM engine: mean and variance, exported to PLY; the box face is occupied.
    let crm = dir.join("crm.mrfmap");
    let args = ["build", s(&data), "-o", s(&crm), "--resolution", "0.05", "--engine", "crm", "--particles", "15", "-q"];
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&["info", s(&crm)]);
    assert!(stdout(&o).contains("engine:      crm") && stdout(&o).contains("particles = 15"), "{}", stdout(&o));
    let crm_map = mrfmap::map::Map::load(&crm).unwrap();
    let face =
        [-0.32, -0.29, -0.26].iter().filter_map(|x| crm_map.occupancy_at([*x, 0.02, 0.3])).fold(0.0f32, f32::max);
    assert!(crm_map.has_variance && face > 0.5, "CRM box face occupancy {face}");
    let ply = dir.join("crm.ply");
    let o = run(&["export", s(&crm), "--ply", s(&ply)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v = mrfmap::outputs::read_ply(&ply).unwrap();
    let var = v.column("variance").expect("CRM exports variance");
    assert!(v.rows.iter().all(|r| (0.0..=0.25).contains(&r[var])));
    let o = run(&[&args[..6], &["--engine", "crm", "--particles", "1"]].concat());
    assert!(!o.status.success() && stderr(&o).contains("particles"), "{}", stderr(&o));

    // Bounds, frames, max range and threads are accepted.
    let o = run(&[
        "build",
        s(&data),
        "-o",
        s(&map),
        "--resolution",
        "0.1",
        "--frames",
        "0,2",
        "--max-range",
        "3",
        "--bounds",
        "-1,-1,-0.5,1,1,1",
        "--threads",
        "1",
        "-q",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (lo, hi) = mrfmap::map::Map::load(&map).unwrap().bounds().unwrap();
    assert!(lo.iter().all(|v| *v >= -1.1) && hi.iter().all(|v| *v <= 1.1), "{lo:?} {hi:?}");
}

#[test]
fn eval_loo_and_compare() {
    let dir = workdir("eval");
    let data = dataset(&dir);
    let map = dir.join("m.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.05", "--exclude", "2", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));

    // Held-out view 2 at 0.05 m: the other three views (90 degrees apart) explain about half of
    // it; a 0.02 m map that includes the view explains nearly all of it.
    let accuracy_of = |json: &str| -> f64 {
        json.split("\"accuracy\": ").nth(1).unwrap().split(',').next().unwrap().parse().unwrap()
    };
    let images = dir.join("img");
    let o = run(&["eval", s(&map), s(&data), "--views", "2", "--json", "--images", s(&images), "--pixel", "40,30"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json = stdout(&o);
    assert!(json.trim_start().starts_with('{') && json.contains("\"views\": [{\"view\": 2"), "{json}");
    let held_out = accuracy_of(&json);
    let fine = dir.join("fine.mrfmap");
    assert!(run(&["build", s(&data), "-o", s(&fine), "--resolution", "0.02", "-q"]).status.success());
    let o = run(&["eval", s(&fine), s(&data), "--views", "2", "--json"]);
    let with_view = accuracy_of(&stdout(&o));
    assert!(
        held_out > 0.3 && with_view > 0.9 && with_view > held_out,
        "held out {held_out}, with the view {with_view}"
    );
    assert!(images.join("view2_accuracy.png").is_file());
    let svg = std::fs::read_to_string(images.join("view2_ray_40_30.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("polyline"));

    // Against the scene: metrics and slices.
    let slices = dir.join("slices");
    let o = run(&["eval", s(&map), "--scene", s(&dir.join("scene.toml")), "--slices", s(&slices), "--slice-z", "0.3"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("ROC AUC") && stdout(&o).contains("precision"), "{}", stdout(&o));
    assert!(slices.join("slice_z0.3_ic.png").is_file());
    // The JSON form carries the occupied voxels' precision and recall, as shares.
    let o = run(&["eval", s(&map), "--scene", s(&dir.join("scene.toml")), "--json"]);
    let json = stdout(&o);
    for key in ["\"precision\": ", "\"recall\": "] {
        let at = json.find(key).unwrap_or_else(|| panic!("no {key} in {json}")) + key.len();
        let value: f64 = json[at..].split([',', '}']).next().unwrap().trim().parse().unwrap();
        assert!((0.0..=1.0).contains(&value), "{key}{value} in {json}");
    }

    let o = run(&["loo", s(&data), "--resolution", "0.1", "--views", "0,3", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("over 2 views"), "{}", stdout(&o));

    let report = dir.join("report");
    let o = run(&["compare", s(&data), "--resolutions", "0.1", "--views", "1", "-o", s(&report), "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let md = std::fs::read_to_string(report.join("report.md")).unwrap();
    assert!(md.contains("| logodds |") && md.contains("truth_logodds_0.1_view1_accuracy.png"), "{md}");
    assert!(report.join("truth_logodds_0.1_view1_accuracy.png").is_file());

    // Errors: nothing to evaluate against, view out of range.
    let o = run(&["eval", s(&map)]);
    assert!(!o.status.success() && stderr(&o).contains("nothing to evaluate"), "{}", stderr(&o));
    let o = run(&["eval", s(&map), s(&data), "--views", "7"]);
    assert!(!o.status.success() && stderr(&o).contains("frame index 7"), "{}", stderr(&o));
}

#[test]
fn bad_dataset_files_give_clear_errors() {
    let dir = workdir("bad");
    let data = dataset(&dir);
    let cam = std::fs::read_to_string(data.join("camera.toml")).unwrap();
    let gt = std::fs::read_to_string(data.join("groundtruth.txt")).unwrap();
    let depth_list = std::fs::read_to_string(data.join("depth.txt")).unwrap();

    // A declared up axis: recorded in the map (which `view` then stands on it), kept by
    // add-noise; a bad declaration names the file.
    std::fs::write(data.join("world.toml"), "up = \"+y\"\n").unwrap();
    let up_map = dir.join("up.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&up_map), "--resolution", "0.1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let info: serde_json::Value = serde_json::from_str(&stdout(&run(&["info", s(&up_map), "--json"]))).unwrap();
    assert_eq!(info["params"]["up"], "+y");
    assert!(run(&["view", s(&up_map), "-o", s(&dir.join("up.png")), "--size", "64x48"]).status.success());
    let noisy = dir.join("noisy-up");
    assert!(run(&["add-noise", s(&data), "-o", s(&noisy), "-q"]).status.success());
    assert_eq!(std::fs::read_to_string(noisy.join("world.toml")).unwrap(), "up = \"+y\"\n");
    std::fs::write(data.join("world.toml"), "up = \"y+\"\n").unwrap();
    build_fails(&data, &[], &["world.toml", "up axis"]);
    std::fs::write(data.join("world.toml"), "down = \"-y\"\n").unwrap();
    build_fails(&data, &[], &["world.toml", "down"]);
    std::fs::remove_file(data.join("world.toml")).unwrap();

    // A map named like another format is refused before any work, pointing at export.
    for name in ["m.bt", "m.PLY"] {
        let o = run(&["build", s(&data), "-o", s(&dir.join(name)), "--resolution", "0.05"]);
        assert!(
            !o.status.success() && stderr(&o).contains("mrfmap export") && !dir.join(name).exists(),
            "{}",
            stderr(&o)
        );
    }

    std::fs::remove_file(data.join("camera.toml")).unwrap();
    build_fails(&data, &[], &["camera.toml", "missing"]);
    std::fs::write(data.join("camera.toml"), cam.replace("fx = ", "focal = ")).unwrap();
    build_fails(&data, &[], &["camera.toml", "focal"]);
    std::fs::write(data.join("camera.toml"), cam.replace("width = 80", "width = 81")).unwrap();
    build_fails(&data, &[], &["000000.png", "80x60", "81x60"]);
    std::fs::write(data.join("camera.toml"), &cam).unwrap();

    // 8-bit RGB PNG where 16-bit depth is expected, and a file that is not a PNG.
    let png_path = data.join("depth/000000.png");
    let good_png = std::fs::read(&png_path).unwrap();
    {
        let f = std::fs::File::create(&png_path).unwrap();
        let mut enc = png::Encoder::new(f, 80, 60);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header().unwrap().write_image_data(&vec![0; 80 * 60 * 3]).unwrap();
    }
    build_fails(&data, &[], &["000000.png", "16-bit"]);
    std::fs::write(&png_path, b"\x89PNG garbage").unwrap();
    build_fails(&data, &[], &["000000.png", "unreadable PNG"]);
    std::fs::write(&png_path, &good_png).unwrap();

    // NaN in a pose; a non-unit quaternion is normalised with a warning.
    let mut lines: Vec<String> = gt.lines().map(String::from).collect();
    let fields: Vec<&str> = lines[1].split_whitespace().collect();
    let nan_line = format!("{} nan {}", fields[0], fields[2..].join(" "));
    let doubled: Vec<String> = fields[4..].iter().map(|q| format!("{}", q.parse::<f64>().unwrap() * 2.0)).collect();
    let scaled_line = format!("{} {}", fields[..4].join(" "), doubled.join(" "));
    lines[1] = nan_line;
    std::fs::write(data.join("groundtruth.txt"), lines.join("\n")).unwrap();
    build_fails(&data, &[], &["groundtruth.txt", "line 2", "NaN"]);
    lines[1] = scaled_line;
    std::fs::write(data.join("groundtruth.txt"), lines.join("\n")).unwrap();
    let map = dir.join("ok.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("normalised"), "{}", stderr(&o));

    // A timestamp given twice: the same pose is fine, two different poses are an error.
    let first_pose = gt.lines().find(|l| !l.starts_with('#')).unwrap().to_string();
    std::fs::write(data.join("groundtruth.txt"), format!("{gt}\n{first_pose}\n")).unwrap();
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut moved: Vec<String> = first_pose.split_whitespace().map(String::from).collect();
    moved[1] = format!("{}", moved[1].parse::<f64>().unwrap() + 0.5);
    std::fs::write(data.join("groundtruth.txt"), format!("{gt}\n{}\n", moved.join(" "))).unwrap();
    build_fails(&data, &[], &["groundtruth.txt", "two different poses"]);

    // No pose near any frame; then an empty dataset; then a listed frame that is missing.
    std::fs::write(data.join("groundtruth.txt"), "100.0 0 0 0 0 0 0 1\n").unwrap();
    build_fails(&data, &[], &["groundtruth.txt", "no depth frame matched"]);
    std::fs::write(data.join("groundtruth.txt"), &gt).unwrap();
    std::fs::write(data.join("depth.txt"), "# nothing here\n").unwrap();
    build_fails(&data, &[], &["depth.txt", "empty dataset"]);
    std::fs::write(data.join("depth.txt"), depth_list.replace("000002.png", "000099.png")).unwrap();
    build_fails(&data, &[], &["depth.txt", "000099.png", "does not exist"]);
    std::fs::write(data.join("depth.txt"), &depth_list).unwrap();

    // Bad arguments.
    build_fails(&data, &["--engine", "octopus"], &["invalid value 'octopus'", "logodds, mrf, crm"]);
    build_fails(&data, &["--exclude", "9"], &["frame index 9", "4 frames"]);
    build_fails(&data, &["--bounds", "1,2,3"], &["bounds"]);
    std::fs::write(dir.join("noise-bad.toml"), "bias = [0.0]\nstd = [0.01]\ncolour = 3\n").unwrap();
    build_fails(&data, &["--noise", s(&dir.join("noise-bad.toml"))], &["noise-bad.toml", "colour"]);
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0"]);
    assert!(!o.status.success() && stderr(&o).contains("positive"), "{}", stderr(&o));
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "-0.1"]);
    assert!(!o.status.success() && stderr(&o).contains("positive"), "{}", stderr(&o));
}

#[test]
fn bad_scene_and_map_files_give_clear_errors() {
    let dir = workdir("scene");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, format!("{SCENE}\n[[pyramid]]\nheight = 1.0\n")).unwrap();
    let o = run(&["simulate", s(&scene), s(&dir.join("out"))]);
    assert!(
        !o.status.success() && stderr(&o).contains("scene.toml") && stderr(&o).contains("pyramid"),
        "{}",
        stderr(&o)
    );
    std::fs::write(&scene, SCENE.replace("radius = 0.3", "radius = -0.3")).unwrap();
    let o = run(&["simulate", s(&scene), s(&dir.join("out"))]);
    assert!(!o.status.success() && stderr(&o).contains("sphere 0"), "{}", stderr(&o));

    let not_map = dir.join("not.mrfmap");
    std::fs::write(&not_map, "ply\nformat ascii 1.0\n").unwrap();
    let o = run(&["info", s(&not_map)]);
    assert!(
        !o.status.success() && stderr(&o).contains("not.mrfmap") && stderr(&o).contains("not an mrfmap"),
        "{}",
        stderr(&o)
    );
    let o = run(&["export", s(&dir.join("absent.mrfmap")), "--ply", s(&dir.join("x.ply"))]);
    assert!(!o.status.success() && stderr(&o).contains("absent.mrfmap"), "{}", stderr(&o));
    assert!(!dir.join("x.ply").exists());
}

#[test]
fn calibrate_and_plot_noise() {
    let dir = workdir("calibrate");
    let data = dataset(&dir);
    let (depth, gt) = (data.join("depth"), data.join("gt_depth"));
    let model = dir.join("learnt.toml");
    let args = ["calibrate", "--measured", s(&depth), "--truth", s(&gt), "-o", s(&model)];
    let o = run(&[&args[..], &["--patch", "40", "--min-samples", "20"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("4 image pairs"), "{}", stdout(&o));
    // The scene's sensor: bias 0.002 z^2, std 0.002 + 0.002 z^2. Check the aggregate at 2 m.
    let learnt = mrfmap::frames::NoiseModel::load(&model).unwrap();
    let (b, sd) = (learnt.bias.eval(2.0), learnt.std.eval(2.0));
    assert!((b - 0.008).abs() < 0.004, "bias at 2 m: {b}");
    assert!((sd / 0.010 - 1.0).abs() < 0.3, "std at 2 m: {sd}");
    assert_eq!(learnt.patches.as_ref().map(|p| (p.rows, p.cols)), Some((2, 2)));

    let png = dir.join("curves.png");
    let o = run(&["noise", "plot", s(&model), "-o", s(&png), "--depth", "1.5"]);
    assert!(o.status.success() && png.exists(), "{}", stderr(&o));
    let o = run(&["noise", "plot", s(&model), "-o", s(&dir.join("x.png")), "--range", "3,1"]);
    assert!(!o.status.success() && stderr(&o).contains("--range"), "{}", stderr(&o));

    // A file missing from one folder is skipped with a warning naming it.
    std::fs::remove_file(gt.join("000002.png")).unwrap();
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("1 image(s)") && stderr(&o).contains("000002.png"), "{}", stderr(&o));

    // Sizes that do not match: an error naming the file, and no output written.
    let small = mrfmap::frames::DepthImage::from_vec(2, 2, vec![1.0; 4]).unwrap();
    mrfmap::source::write_depth_png(&gt.join("000001.png"), &small, 5000.0).unwrap();
    let fresh = dir.join("fresh.toml");
    let o = run(&["calibrate", "--measured", s(&depth), "--truth", s(&gt), "-o", s(&fresh)]);
    assert!(!o.status.success() && stderr(&o).contains("000001.png") && stderr(&o).contains("2x2"), "{}", stderr(&o));
    assert!(!fresh.exists());

    // Not a PNG.
    std::fs::write(gt.join("000001.png"), b"not a png").unwrap();
    let o = run(&["calibrate", "--measured", s(&depth), "--truth", s(&gt), "-o", s(&fresh)]);
    assert!(stderr(&o).contains("000001.png") && stderr(&o).contains("unreadable PNG"), "{}", stderr(&o));

    // No common names, and no depth scale to be found.
    let o = run(&["calibrate", "--measured", s(&depth), "--truth", s(&dir), "-o", s(&fresh)]);
    assert!(stderr(&o).contains("no PNG file names appear in both"), "{}", stderr(&o));
    let o = run(&["calibrate", "--measured", s(&data), "--truth", s(&gt), "-o", s(&fresh)]);
    assert!(stderr(&o).contains("--depth-scale"), "{}", stderr(&o));
}

/// `add-noise`: a noisy twin of a dataset (Kinect model or a noise.toml), the input's depth as
/// its gt_depth, seeded, and nothing written when anything fails.
#[test]
fn add_noise_writes_a_noisy_twin() {
    use mrfmap::source::Dataset;
    let dir = workdir("add-noise");
    let data = dataset(&dir);
    let out = dir.join("noisy");
    let o = run(&["add-noise", s(&data), "-o", s(&out), "--seed", "4"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("4 frames") && stdout(&o).contains("depth levels"), "{}", stdout(&o));
    let (input, noisy) = (Dataset::open(&data).unwrap(), Dataset::open(&out).unwrap());
    assert_eq!(noisy.len(), input.len());
    assert!(noisy.noise().is_some(), "noise.toml: the model to map with");
    let fb = mrfmap::source::StructuredLight::kinect().baseline * noisy.camera().fx;
    for i in 0..input.len() {
        let clean = input.frame(i).unwrap();
        let got = noisy.frame(i).unwrap();
        assert_eq!(noisy.truth_depth(i).unwrap().unwrap(), clean.depth, "gt_depth is the input's depth");
        assert_eq!(got.pose, clean.pose);
        assert_ne!(got.depth, clean.depth);
        // Kinect depth levels: f b / (k / 8) m, to the 0.2 mm the scene's 5000 scale stores.
        for &z in got.depth.data().iter().filter(|&&z| z > 0.0) {
            let k = 8.0 * fb / f64::from(z);
            assert!((fb / (k.round() / 8.0) - f64::from(z)).abs() < 2e-4, "{z} m is not a disparity level");
        }
    }
    let again = dir.join("again");
    assert!(run(&["add-noise", s(&data), "-o", s(&again), "--seed", "4", "-q"]).status.success());
    for i in 0..input.len() {
        let name = format!("depth/{i:06}.png");
        assert_eq!(std::fs::read(out.join(&name)).unwrap(), std::fs::read(again.join(&name)).unwrap(), "seeded");
    }

    // A noise.toml model.
    let model = dir.join("model.toml");
    std::fs::write(&model, "bias = [0.0]\nstd = [0.01]\n").unwrap();
    let gauss = dir.join("gauss");
    let o = run(&["add-noise", s(&data), "-o", s(&gauss), "--model", s(&model), "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        std::fs::read_to_string(gauss.join("noise.toml")).unwrap(),
        mrfmap::frames::NoiseModel::load(&model).unwrap().to_toml()
    );

    // Refusals: an existing output (left as it was), a model that is neither, --shadows with a
    // file, a patch grid that does not fit the camera.
    let o = run(&["add-noise", s(&data), "-o", s(&out)]);
    assert!(!o.status.success() && stderr(&o).contains("already exists"), "{}", stderr(&o));
    assert!(Dataset::open(&out).is_ok());
    let o = run(&["add-noise", s(&data), "-o", s(&dir.join("x")), "--model", "kinnect"]);
    assert!(!o.status.success() && stderr(&o).contains("kinnect"), "{}", stderr(&o));
    let o = run(&["add-noise", s(&data), "-o", s(&dir.join("x")), "--model", s(&model), "--shadows"]);
    assert!(!o.status.success() && stderr(&o).contains("--shadows"), "{}", stderr(&o));
    std::fs::write(
        &model,
        "bias = [0.0]\nstd = [0.01]\n[patches]\nsize = 8\nrows = 1\ncols = 1\nbias = [[0.0]]\nstd = [[0.01]]\n",
    )
    .unwrap();
    let o = run(&["add-noise", s(&data), "-o", s(&dir.join("x")), "--model", s(&model)]);
    assert!(!o.status.success() && stderr(&o).contains("patch grid"), "{}", stderr(&o));

    // A frame that cannot be read half-way: the error names it and nothing is left behind.
    std::fs::write(data.join("depth/000002.png"), b"not a png").unwrap();
    let o = run(&["add-noise", s(&data), "-o", s(&dir.join("broken"))]);
    assert!(!o.status.success() && stderr(&o).contains("000002.png"), "{}", stderr(&o));
    assert!(!stderr(&o).contains("panicked"));
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().map(|e| e.file_name()).collect();
    assert!(!left.iter().any(|n| n.to_string_lossy().contains("broken")), "{left:?}");
}

/// `experiment mrfmap-table2` end to end on the small scene: noise added, thresholds wider than
/// the orbit make frame 0 the only keyframe, every engine and both voxelised surfaces are scored on the
/// other three at the dataset's placement of the grid and at a shifted one, and the report,
/// JSON and pictures are written.
#[test]
fn mrfmap_table2_experiment_writes_its_report() {
    let dir = workdir("table2");
    let data = dataset(&dir);
    let out = dir.join("t2");
    let args = ["experiment", "mrfmap-table2", s(&data), "-o", s(&out), "--resolutions", "0.1", "-q"];
    let o =
        run(&[&args[..], &["--translation", "100", "--rotation", "100", "--grid-offsets", "1", "--surfaces"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("| mrf |") && report.contains("paper MRFMap"), "{report}");
    assert!(report.contains("| surfaces of every frame |") && report.contains("Where the grid cuts"), "{report}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    assert_eq!(json["keyframes"], serde_json::json!([0]));
    assert_eq!(json["held_out_views"], serde_json::json!([1, 2, 3]));
    let placement = &json["grid_placements"][0];
    let shift = placement["shift_voxels"].as_array().unwrap();
    assert!(shift.len() == 3 && shift.iter().all(|f| (0.0..1.0).contains(&f.as_f64().unwrap())), "{placement}");
    let names =
        |rows: &serde_json::Value| rows.as_array().unwrap().iter().map(|r| r["engine"].clone()).collect::<Vec<_>>();
    assert_eq!(names(&json["rows"]), names(&placement["rows"]));
    let accuracy = |row: &serde_json::Value| row["accuracy_constant_5cm"]["mean"].as_f64().unwrap();
    let rows = json["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 5);
    for (row, moved) in rows.iter().zip(placement["rows"].as_array().unwrap()) {
        for key in ["accuracy_constant_5cm", "accuracy_model_std"] {
            for row in [row, moved] {
                let views = row[key]["views"].as_array().unwrap();
                assert!(!views.is_empty() && views.iter().all(|a| (0.0..=1.0).contains(&a.as_f64().unwrap())), "{row}");
            }
        }
        let tag = format!("{}_10cm", row["engine"].as_str().unwrap());
        let pictured =
            out.join(format!("map_{tag}.png")).is_file() && out.join(format!("accuracy_{tag}_view2.png")).is_file();
        // Pictures of the engines' maps, not of the surfaces.
        assert_eq!(pictured, !tag.starts_with("surfaces"), "{tag}");
    }
    // With voxels finer than the tolerance, the surfaces of every frame, the scored views' own
    // among them, score well wherever the grid lies (the views and the map moved together).
    let fine = dir.join("fine");
    let o = run(&[
        "experiment",
        "mrfmap-table2",
        s(&data),
        "-o",
        s(&fine),
        "--resolutions",
        "0.02",
        "--engines",
        "logodds",
        "--grid-offsets",
        "2",
        "--surfaces",
        "--translation",
        "100",
        "--rotation",
        "100",
        "-q",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fine.join("results.json")).unwrap()).unwrap();
    for rows in [&json["rows"], &json["grid_placements"][0]["rows"], &json["grid_placements"][1]["rows"]] {
        assert_eq!(rows[1]["engine"], "surfaces of every frame");
        assert!(accuracy(&rows[1]) > 0.8, "{rows}");
    }
    // The noisy dataset stays, and a second run replaces it.
    assert!(mrfmap::source::Dataset::open(&out.join("noisy")).is_ok());
    let o = run(&[&args[..], &["--translation", "100", "--rotation", "100", "--engines", "logodds"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    // Without `--surfaces`, the engines alone.
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    assert_eq!(names(&json["rows"]), vec![serde_json::json!("logodds")]);
    // Every frame a keyframe: nothing to score on, said before any map is built.
    let o = run(&[&args[..], &["--translation", "0.001", "--rotation", "0.001"]].concat());
    assert!(!o.status.success() && stderr(&o).contains("every frame"), "{}", stderr(&o));
}

/// `experiment crm-icl` end to end on the small scene: steps every two frames and after the
/// last, scores in range, curves written.
#[test]
fn crm_icl_experiment_writes_its_curves() {
    let dir = workdir("crm-icl");
    let data = dataset(&dir);
    let out = dir.join("icl");
    // (A folder of its own per run: `--clean` writes no noisy copy, so creates it alone.)
    let experiment = |out: &std::path::Path, extra: &[&str]| -> serde_json::Value {
        let base = ["experiment", "crm-icl", s(&data), "-o", s(out), "--resolution", "0.1", "--every", "3"];
        let o = run(&[&base[..], &["--particles", "15", "-q"], extra].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap()
    };
    let json = experiment(&out, &[]);
    let steps = json["steps"].as_array().unwrap();
    assert_eq!(steps.iter().map(|s| s["frames"].as_u64().unwrap()).collect::<Vec<_>>(), vec![3, 4]);
    for s in steps {
        for method in ["crm", "logodds"] {
            let (mae, pcc) = (s[method]["mae"].as_f64().unwrap(), s[method]["pcc_sigma_error"].as_f64().unwrap());
            assert!((0.0..=1.0).contains(&mae) && (-1.0..=1.0).contains(&pcc), "{s}");
        }
    }
    assert!(json["crm_pcc_above_logodds_at_every_step"].is_boolean());
    assert!(out.join("mae.png").is_file() && out.join("pcc.png").is_file());
    assert!(std::fs::read_to_string(out.join("report.md")).unwrap().contains("| 4 |"));
    // Fed the noise-free frames (`--clean`), log-odds after the last one is the reference
    // itself, so it ranks every voxel right (AUC 1), which it does not with noise.
    let auc = |json: &serde_json::Value| json["steps"][1]["logodds"]["auc"].as_f64().unwrap();
    assert!(auc(&json) < 1.0, "{json}");
    let json = experiment(&dir.join("clean"), &["--clean"]);
    assert!(json["clean"].as_bool().unwrap() && auc(&json) == 1.0, "{json}");
    // Against the frames' surfaces instead (`surface_truth`, tested on its own).
    let json = experiment(&dir.join("surface"), &["--clean", "--reference", "surface"]);
    assert!(json["reference"] == "surface" && json["reference_occupied"].as_u64().unwrap() > 0, "{json}");
}

/// `export --bt/--ot`: read back by our reader always, and by OctoMap's own `convert_octree`
/// (Debian's octomap-tools) where it is installed.
#[test]
fn octomap_export() {
    let dir = workdir("octomap");
    let map = logodds_map(&dir);
    let (bt, ot) = (dir.join("m.bt"), dir.join("m.ot"));
    let o = run(&["export", s(&map), "--bt", s(&bt), "--ot", s(&ot)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let loaded = mrfmap::map::Map::load(&map).unwrap();
    let ours_bt = mrfmap::outputs::read_octomap(&bt).unwrap();
    let ours_ot = mrfmap::outputs::read_octomap(&ot).unwrap();
    assert_eq!(ours_ot.leaves.len(), loaded.voxels.len());
    let occupied: usize = ours_bt.leaves.iter().filter(|l| l.value > 0.0).map(|l| l.voxels().count()).sum();
    assert_eq!(occupied, loaded.occupied_count());

    let o = run(&["export", s(&map)]);
    assert!(!o.status.success() && stderr(&o).contains("--ply"), "{}", stderr(&o));

    let Ok(out) = Command::new("convert_octree").arg(&bt).arg(dir.join("from_bt.ot")).output() else {
        println!("skipped the OctoMap check: convert_octree (Debian's octomap-tools) is not installed");
        return;
    };
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!text.contains("ERROR"), "OctoMap refused our .bt: {text}");
    let theirs = mrfmap::outputs::read_octomap(&dir.join("from_bt.ot")).unwrap();
    assert_eq!(theirs.nodes, ours_bt.nodes, "OctoMap read the same tree");
    let theirs_occupied: usize = theirs.leaves.iter().filter(|l| l.value > 0.0).map(|l| l.voxels().count()).sum();
    assert_eq!(theirs_occupied, occupied);
    let out = Command::new("convert_octree").arg(&ot).arg(dir.join("from_ot.ot")).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!text.contains("ERROR") && text.contains(&format!("Done ({} nodes)", ours_ot.nodes)), "{text}");
    assert_eq!(mrfmap::outputs::read_octomap(&dir.join("from_ot.ot")).unwrap(), ours_ot);
}

#[test]
fn view_pictures_and_slices() {
    let dir = workdir("view");
    let map = logodds_map(&dir);
    let png = dir.join("v.png");
    let o = run(&["view", s(&map), "-o", s(&png), "--size", "320x240", "--color", "sigma"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap()));
    let info = decoder.read_info().unwrap().info().clone();
    assert_eq!((info.width, info.height), (320, 240));
    // Looking straight down on the box top (z = 0.6) from above: the centre pixel is a voxel.
    let o = run(&["view", s(&map), "-o", s(&png), "--eye", "0,0,3", "--target", "0,0.001,0", "--size", "64x48"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut reader =
        png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap())).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    reader.next_frame(&mut buf).unwrap();
    let centre = (24 * 64 + 32) * 3;
    assert_ne!(&buf[centre..centre + 3], &[255, 255, 255], "the box top is drawn at the centre");
    let o = run(&["view", s(&map), "-o", s(&png), "--up", "-y", "--size", "64x48"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let slice = dir.join("s.png");
    let o = run(&["view", s(&map), "-o", s(&slice), "--slice", "z=0.3"]);
    assert!(o.status.success() && slice.exists(), "{}", stderr(&o));
    for (args, needle) in [
        (vec!["--slice", "w=1"], "axis"),
        (vec!["--slice", "z=40"], "no voxels at z = 40"),
        (vec!["--eye", "1,2"], "--eye"),
        (vec!["--size", "0x10"], "--size"),
        (vec!["--up", "+w"], "up axis"),
    ] {
        let bad = dir.join("bad.png");
        let o = run(&[&["view", s(&map), "-o", s(&bad)][..], &args[..]].concat());
        assert!(!o.status.success() && stderr(&o).contains(needle) && !bad.exists(), "{args:?}: {}", stderr(&o));
    }
}

#[test]
fn crm_2d_experiment_writes_its_report() {
    let dir = workdir("crm2d");
    let out = dir.join("crm2d");
    let o = run(&["experiment", "crm-2d", "-o", s(&out), "--repeat", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in ["| MAE | CRM, 101 particles", "| PCC(sigma, abs error) | log-odds", "ISM sweep at 1 s noise"] {
        assert!(report.contains(needle), "missing {needle:?}");
    }
    // 48 sweep rows.
    assert_eq!(
        report
            .lines()
            .filter(|l| l.starts_with("| 0.05 |") || l.starts_with("| 0.20 |") || l.starts_with("| 0.40 |"))
            .count(),
        48
    );
    assert!(out.join("crm2d_maps.png").is_file());
}

#[test]
fn scaling_keyframe_curve_alone() {
    let dir = workdir("scaling");
    let data = dataset(&dir);
    let out = dir.join("scaling");
    let o = run(&["scaling", s(&data), "-o", s(&out), "--curves", "keyframes", "--keyframes", "1,2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    let rows: Vec<&str> = report.lines().filter(|l| l.starts_with("| 1 |") || l.starts_with("| 2 |")).collect();
    assert_eq!(rows.len(), 2, "{report}");
    // Two small maps converge well within the sweeps allowed.
    assert!(rows.iter().all(|r| r.contains("| true |")), "{report}");
    assert!(!report.contains("vs resolution") && report.contains("`mrf_vs_keyframes.png`."), "{report}");
    assert!(out.join("mrf_vs_keyframes.png").is_file() && !out.join("time_vs_resolution.png").exists());
    // Refused before any work: no keyframes, and more views than memory holds.
    for (count, needle) in [("0", "at least 1"), ("100000", "fewer --keyframes")] {
        let o = run(&["scaling", s(&data), "-o", s(&out), "--curves", "keyframes", "--keyframes", count]);
        assert!(!o.status.success() && stderr(&o).contains(needle), "{}", stderr(&o));
    }
}

#[test]
fn logodds_marking_walk_and_project_build_the_same_map() {
    let dir = workdir("marking");
    let projected = logodds_map(&dir);
    let data = dir.join("data");
    let walked = dir.join("walk.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&walked), "--resolution", "0.05", "--marking", "walk", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, b) = (mrfmap::map::Map::load(&projected).unwrap(), mrfmap::map::Map::load(&walked).unwrap());
    assert!(a.voxels.len() > 1000);
    let differ = a.voxels.iter().filter(|(k, v)| b.voxels.get(*k) != Some(*v)).count();
    assert_eq!((a.voxels.len(), differ), (b.voxels.len(), 0), "walking and projecting disagree");
    let o = run(&["build", s(&data), "-o", s(&dir.join("x.mrfmap")), "--resolution", "0.05", "--marking", "fly"]);
    assert!(!o.status.success() && stderr(&o).contains("fly") && stderr(&o).contains("walk"), "{}", stderr(&o));
    assert!(!dir.join("x.mrfmap").exists());
}

#[test]
fn mrf_reference_metric_and_bad_values_and_plain_errors() {
    let dir = workdir("mrf-modes");
    let data = dataset(&dir);
    let map = dir.join("sum.mrfmap");
    let o = run(&["build", s(&data), "-o", s(&map), "--resolution", "0.05", "--engine", "mrf", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(mrfmap::map::Map::load(&map).unwrap().occupied_count() > 0);
    // Both metrics score the map; the reference metric's name reaches the report.
    for metric in ["algorithms", "reference"] {
        let o = run(&["eval", s(&dir.join("sum.mrfmap")), s(&data), "--views", "0", "--metric", metric, "--json"]);
        assert!(o.status.success() && stdout(&o).contains("\"accuracy\""), "{}", stderr(&o));
    }
    let o = run(&["eval", s(&dir.join("sum.mrfmap")), s(&data), "--metric", "exit"]);
    assert!(!o.status.success() && stderr(&o).contains("reference"), "{}", stderr(&o));
    build_fails(&data, &["--engine", "mrf", "--iterations", "0"], &["iterations"]);
    build_fails(&data, &["--engine", "mrf", "--tolerance", "0"], &["tolerance"]);
    build_fails(&data, &["--engine", "mrf", "--damping", "1"], &["damping", "[0, 1)"]);
    build_fails(&data, &["--engine", "mrf", "--ray-spacing=-1"], &["ray-spacing", "0 or a positive number"]);
    build_fails(&data, &["--engine", "mrf", "--min-evidence=-1"], &["min-evidence", "0 or a positive number"]);
    let until = dir.join("until.mrfmap");
    let o = run(&[
        "build",
        s(&data),
        "-o",
        s(&until),
        "--resolution",
        "0.05",
        "--engine",
        "mrf",
        "--tolerance",
        "0.01",
        "--iterations",
        "20",
        "--verbose",
    ]);
    // `--verbose` adds a line per sweep with the tiles and rays it traced.
    assert!(o.status.success() && stderr(&o).contains("sweeps"), "{}", stderr(&o));
    assert!(stderr(&o).contains("sweep 1: ") && stderr(&o).contains(" rays traced"), "{}", stderr(&o));
    let o = run(&["info", s(&data), "--verbose", "--quiet"]);
    assert!(!o.status.success() && stderr(&o).contains("--quiet"), "{}", stderr(&o));
    let until = mrfmap::map::Map::load(&until).unwrap();
    assert_eq!(until.params.get("tolerance").map(String::as_str), Some("0.01"));
    // `bench` takes the MRF's ray spacing, for its full builds and its added keyframe alike,
    // and refuses it for the other engines.
    let o = run(&[
        "bench",
        s(&data),
        "--engine",
        "mrf",
        "--resolutions",
        "0.1",
        "--repeat",
        "1",
        "--incremental",
        "--ray-spacing",
        "1",
    ]);
    assert!(o.status.success() && stdout(&o).contains("incremental_ms"), "{}", stderr(&o));
    let o = run(&["bench", s(&data), "--resolutions", "0.1", "--ray-spacing", "1"]);
    assert!(!o.status.success() && stderr(&o).contains("--ray-spacing is for --engine mrf"), "{}", stderr(&o));
    // A missing output folder is refused before any work, and the OS message is said once.
    let o = run(&["build", s(&data), "-o", s(&dir.join("no/such/m.mrfmap")), "--resolution", "0.05"]);
    assert!(!o.status.success() && stderr(&o).contains("output folder"), "{}", stderr(&o));
    let o = run(&["info", s(&dir)]);
    assert!(!o.status.success() && stderr(&o).matches("os error").count() == 1, "{}", stderr(&o));
}

#[test]
fn query_json_contract_and_map_operations() {
    use mrfmap::map::Map;
    use mrfmap::outputs::{QueryOptions, query_box, query_point, query_segment};
    let dir = workdir("query");
    let map_path = logodds_map(&dir);
    let map = Map::load(&map_path).unwrap();
    let csv = dir.join("points.csv");
    std::fs::write(&csv, "x,y,z\n# the box's face, then free space\n-0.31,0.02,0.3\n\n-0.6,0.02,0.3\n").unwrap();
    let o = run(&[
        "query",
        s(&map_path),
        "--segment",
        "-1.5,0.02,0.3:1.5,0.02,0.3",
        "--segment=-1.5,-1.5,1.5:-1.4,-1.5,1.5",
        "--points",
        s(&csv),
        "--box=-0.2,-0.2,0.1,0.2,0.2,0.5",
        "--unknown",
        "0.3",
        "--k",
        "1",
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_str(&stdout(&o)).expect("one JSON object");
    let opts = QueryOptions { unknown: 0.3, k: 1.0, ..Default::default() };
    let segs = v["segments"].as_array().unwrap();
    assert_eq!(segs.len(), 2);
    let through = query_segment(&map, [-1.5, 0.02, 0.3], [1.5, 0.02, 0.3], &opts);
    assert_eq!(segs[0]["p_free"].as_f64().unwrap(), through.p_free);
    assert_eq!(segs[0]["p_free_lcb"].as_f64().unwrap(), through.p_free_lcb);
    assert_eq!(segs[0]["expected_occupied"].as_f64().unwrap(), through.expected_occupied);
    let hit: Vec<f64> = segs[0]["first_hit"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    assert!(hit[0] < -0.25 && hit[0] > -0.4, "the path through the box hits its -x face first: {hit:?}");
    assert!(through.p_free < 0.01);
    // Above the scene: nothing known, so the prior answers and nothing is hit.
    assert!(segs[1]["first_hit"].is_null() && segs[1]["unknown"] == segs[1]["voxels"]);
    let points = v["points"].as_array().unwrap();
    assert_eq!(points.len(), 2, "header, comment and blank lines skipped");
    let face = query_point(&map, [-0.31, 0.02, 0.3], &opts);
    assert_eq!(points[0]["occupancy"].as_f64().unwrap(), face.occupancy);
    assert_eq!(points[0]["known"], true);
    let boxes = v["boxes"].as_array().unwrap();
    let region = mrfmap::map::Aabb::parse("-0.2,-0.2,0.1,0.2,0.2,0.5").unwrap();
    let b = query_box(&map, &region, &opts).unwrap();
    assert_eq!(boxes[0]["unknown"].as_u64().unwrap(), b.unknown);
    assert_eq!(boxes[0]["occupied"].as_u64().unwrap(), b.occupied);

    // Bad input names what is wrong.
    std::fs::write(&csv, "1,2,3\n4,five,6\n").unwrap();
    let o = run(&["query", s(&map_path), "--points", s(&csv)]);
    assert!(!o.status.success() && stderr(&o).contains("points.csv:2"), "{}", stderr(&o));
    let o = run(&["query", s(&map_path), "--segment", "1,2:3,4,5"]);
    assert!(!o.status.success() && stderr(&o).contains("X,Y,Z:X,Y,Z"), "{}", stderr(&o));
    let o = run(&["query", s(&map_path), "--segment", "0,0,0:1,1,1", "--unknown", "2"]);
    assert!(!o.status.success() && stderr(&o).contains("[0, 1]"), "{}", stderr(&o));
    // Far endpoints are refused at once (they walked for minutes, or at 1e308 overflowed into
    // "free"), naming the argument; a long but sane path is answered.
    for far in ["-1e9,0,0:1e9,0,0", "-1e308,0,0:1e308,0,0", "-1e20,1,1:1e20,1,1"] {
        let t = std::time::Instant::now();
        let o = run(&["query", s(&map_path), "--segment", far]);
        assert!(!o.status.success() && stderr(&o).contains("clip it") && stderr(&o).contains(far), "{}", stderr(&o));
        assert!(t.elapsed().as_secs() < 20, "{far} took {:?}", t.elapsed());
    }
    let o = run(&["query", s(&map_path), "--polyline", "0,0,0:1e9,0,0:0,0,1"]);
    assert!(!o.status.success() && stderr(&o).contains("--polyline"), "{}", stderr(&o));
    let o = run(&["query", s(&map_path), "--segment", "-500,0,0.3:500,0,0.3", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));

    // Crop and clear split the map; merging the halves gives it back; diff sees the cleared box.
    let (inner, outer, merged) = (dir.join("in.mrfmap"), dir.join("out.mrfmap"), dir.join("merged.mrfmap"));
    let region = "--box=-0.5,-0.5,0,0.5,0.5,1";
    assert!(run(&["crop", s(&map_path), region, "-o", s(&inner)]).status.success());
    assert!(run(&["clear", s(&map_path), region, "-o", s(&outer)]).status.success());
    let o = run(&["merge", s(&inner), s(&outer), "-o", s(&merged)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let back = Map::load(&merged).unwrap();
    assert_eq!(back.voxels.len(), map.voxels.len());
    assert!(map.voxels.iter().all(|(k, v)| back.voxels.get(k) == Some(v)));
    let changed = dir.join("changed.ply");
    let o = run(&["diff", s(&outer), s(&map_path), "-o", s(&changed)]);
    assert!(o.status.success() && stdout(&o).contains("unknown -> occupied"), "{}", stdout(&o));
    let inner_map = Map::load(&inner).unwrap();
    assert_eq!(mrfmap::outputs::read_ply(&changed).unwrap().rows.len(), inner_map.voxels.len());

    // A Foxglove scene of the map: an MCAP file (magic bytes at both ends).
    let mcap = dir.join("m.mcap");
    let o = run(&["export", s(&map_path), "--mcap", s(&mcap), "--color", "sigma"]);
    assert!(o.status.success() && stdout(&o).contains(&format!("{} cubes", map.occupied_count())), "{}", stdout(&o));
    let bytes = std::fs::read(&mcap).unwrap();
    assert!(bytes.starts_with(b"\x89MCAP0\r\n") && bytes.ends_with(b"\x89MCAP0\r\n"));
    let o = run(&["--max-memory", "4M", "export", s(&map_path), "--mcap", s(&dir.join("big.mcap"))]);
    assert!(!o.status.success() && stderr(&o).contains("a Foxglove scene of"), "{}", stderr(&o));

    // The floor-to-head slab as a map_server grid: occupied where the box stands.
    let yaml = dir.join("grid.yaml");
    let o = run(&["project", s(&map_path), "--z-min", "0.1", "--z-max", "0.5", "-o", s(&yaml)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let g = mrfmap::outputs::read_map_server(&yaml).unwrap();
    let cell = |x: f64, y: f64| {
        let (i, j) = (((x - g.origin[0]) / g.resolution) as usize, ((y - g.origin[1]) / g.resolution) as usize);
        g.cells[j * g.width + i]
    };
    assert_eq!(cell(-0.29, 0.02), Some(true), "the box");
    assert_eq!(cell(-1.0, 0.02), Some(false), "free space in front of it");
}

/// A CARMEN log of a 4 m x 4 m square room seen from three poses (FLASER, 180 beams, pi/n
/// apart), with one no-return beam per scan.
fn square_room_log(dir: &Path) -> PathBuf {
    let mut text = String::from("# synthetic\nPARAM robot_frontlaser_offset 0.0 nohost 0\n");
    for (i, [x, y, theta]) in [[0.0, 0.0, 0.0], [0.5, 0.3, 1.0], [-0.6, -0.4, 2.0], [0.2, -0.5, 4.0]].iter().enumerate()
    {
        text.push_str(&format!("ODOM {x} {y} {theta} 0 0 0 {i} h {i}\nFLASER 180"));
        for k in 0..180 {
            let a = theta - std::f64::consts::FRAC_PI_2 + k as f64 * std::f64::consts::PI / 180.0;
            let (dx, dy) = (a.cos(), a.sin());
            let t = [(2.0 - x) / dx, (-2.0 - x) / dx, (2.0 - y) / dy, (-2.0 - y) / dy]
                .into_iter()
                .filter(|t| *t > 0.0)
                .fold(f64::INFINITY, f64::min);
            let r = if k == 90 { 81.83 } else { t };
            text.push_str(&format!(" {r:.3}"));
        }
        text.push_str(&format!(" {x} {y} {theta} {x} {y} {theta} {i}.5 host {i}.5\nNEFF 10\n"));
    }
    let path = dir.join("room.log");
    std::fs::write(&path, text).unwrap();
    path
}

/// The 2D grid at `yaml` shows the square room of `square_room_log`: walls at x = +-2 m
/// occupied, the inside free.
fn check_square_room(yaml: &Path, what: &str) {
    let g = mrfmap::outputs::read_map_server(yaml).unwrap();
    let cell = |x: f64, y: f64| {
        let (i, j) = (((x - g.origin[0]) / g.resolution) as usize, ((y - g.origin[1]) / g.resolution) as usize);
        g.cells[j * g.width + i]
    };
    // Ranges are written to the millimetre, so a wall's hits land on either side of it.
    let wall = |x: f64, y: f64| cell(x - 0.01, y) == Some(true) || cell(x + 0.01, y) == Some(true);
    assert!(wall(2.0, 0.52), "{what}: the east wall");
    assert!(wall(-2.0, -0.27), "{what}: the west wall");
    assert_eq!(cell(0.8, 0.1), Some(false), "{what}: the room");
}

#[test]
fn laser_log_build_grid2d_view_and_experiment() {
    let dir = workdir("laser");
    let log = square_room_log(&dir);
    let map = dir.join("room.mrfmap");
    for engine in ["logodds", "crm"] {
        let o = run(&["build", s(&log), "--engine", engine, "--resolution", "0.05", "-o", s(&map), "-q"]);
        assert!(o.status.success() && stdout(&o).contains("4 frames"), "{}{}", stdout(&o), stderr(&o));
        let yaml = dir.join(format!("{engine}.yaml"));
        let o = run(&["export", s(&map), "--grid2d", s(&yaml), "--sigma"]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(dir.join(format!("{engine}-sigma.pgm")).is_file());
        check_square_room(&yaml, engine);
        // The picture of a one-layer map is the 2D grid with its sigma, no camera needed.
        let png = dir.join(format!("{engine}.png"));
        let o = run(&["view", s(&map), "-o", s(&png)]);
        assert!(o.status.success() && png.is_file(), "{}", stderr(&o));
    }
    // A beam without a return (81.9 m: a SICK's "no return") clears 5 m by default, and up
    // to the laser's range with --miss-range inf.
    let miss = dir.join("miss.log");
    std::fs::write(&miss, "FLASER 3 1.0 81.9 1.0 0 0 0 0 0 0 1 h 1\n").unwrap();
    let reach = |extra: &[&str]| {
        let o = run(&[&["build", s(&miss), "--resolution", "0.1", "-o", s(&map), "-q"], extra].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let o = run(&["info", s(&map), "--json"]);
        let v: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
        v["bounds"][1][0].as_f64().unwrap()
    };
    // The miss is 30 degrees right of ahead: x reaches 5 cos 30 = 4.33 m, or 80 cos 30 = 69 m.
    let (short, long) = (reach(&[]), reach(&["--miss-range", "inf"]));
    assert!((4.2..4.5).contains(&short) && (68.0..70.0).contains(&long), "{short} {long}");
    assert!(!run(&["build", s(&miss), "--resolution", "0.1", "-o", s(&map), "--miss-range", "-1"]).status.success());

    // The MRF takes depth images only: said before any memory estimate (which cannot size an
    // MRF from scans and used to refuse it as needing hundreds of GiB).
    let o = run(&["--max-memory", "1M", "build", s(&log), "--engine", "mrf", "--resolution", "0.05", "-o", s(&map)]);
    assert!(!o.status.success() && stderr(&o).contains("depth images only"), "{}", stderr(&o));
    assert!(!stderr(&o).contains("would need"), "{}", stderr(&o));

    // The experiment runs end to end and writes its report and pictures.
    let out = dir.join("exp");
    let o = run(&["experiment", "crm-laser", s(&log), "-o", s(&out), "--subset", "3", "--repeat", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("## Results") && report.contains("CRM, 101 particles") && report.contains("pi / (n - 1)"));
    // results.json holds the same scores and the issue's two checks, consistent with them.
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    let (methods, sweep) = (v["methods"].as_array().unwrap(), v["sweep"].as_array().unwrap());
    assert_eq!((methods.len(), sweep.len()), (3, 48));
    let crm_mae = methods[0]["mae"].as_f64().unwrap();
    let beaten = sweep.iter().filter(|s| crm_mae < s["mae"].as_f64().unwrap()).count();
    assert_eq!(v["crm_mae_beats_settings"].as_u64(), Some(beaten as u64));
    assert_eq!(v["crm_mae_below_every_setting"].as_bool(), Some(beaten == 48));
    let below = methods[0]["ic_2"].as_f64().unwrap() < methods[2]["ic_2"].as_f64().unwrap();
    assert_eq!(v["crm_ic_2_below_paper_ism"].as_bool(), Some(below));
    assert!(report.contains(&format!("{:.4}", crm_mae)), "the report shows the same MAE");
    for png in ["reference.png", "crm.png", "crm15.png", "logodds-paper-ism.png"] {
        assert!(out.join(png).is_file(), "{png}");
    }

    // A bad line names the file and the line; nothing is written.
    let bad = dir.join("bad.log");
    std::fs::write(
        &bad,
        "ODOM 0 0 0 0 0 0 0 h 0\nFLASER 2 1.0 1.5 0 0 0 0 0 0 1 h 1\nFLASER 2 1.0 -1.5 0 0 0 0 0 0 2 h 2\n",
    )
    .unwrap();
    let out_map = dir.join("bad.mrfmap");
    let o = run(&["build", s(&bad), "--resolution", "0.05", "-o", s(&out_map)]);
    let err = stderr(&o);
    assert!(
        !o.status.success() && err.contains("bad.log") && err.contains("line 3") && err.contains("negative"),
        "{err}"
    );
    assert!(!out_map.exists());
}

#[test]
fn runaway_work_is_refused_before_it_starts_and_argument_errors_look_like_errors() {
    let dir = workdir("limits");
    let data = dataset(&dir);
    let out = dir.join("m.mrfmap");
    // A resolution no machine can hold: refused at once, with the estimate and a way out.
    let t = std::time::Instant::now();
    let o = run(&["build", s(&data), "-o", s(&out), "--resolution", "1e-9"]);
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("would need about") && err.contains("--resolution"), "{err}");
    assert!(t.elapsed().as_secs() < 20 && !out.exists());
    // The limit is settable; a small one refuses an ordinary build.
    let o = run(&["--max-memory", "1M", "build", s(&data), "-o", s(&out), "--resolution", "0.05"]);
    assert!(!o.status.success() && stderr(&o).contains("limit of 1.0 MiB"), "{}", stderr(&o));
    let o = run(&["build", s(&data), "-o", s(&out), "--resolution", "0.05", "--engine", "mrf", "--max-memory", "lots"]);
    assert!(!o.status.success() && stderr(&o).contains("memory size \"lots\""), "{}", stderr(&o));
    // The variable is read as strictly as the flag (it was ignored when it did not parse).
    let o = bin()
        .args(["build", s(&data), "-o", s(&out), "--resolution", "0.05"])
        .env("MRFMAP_MAX_MEMORY", "abc")
        .output()
        .unwrap();
    assert!(!o.status.success() && stderr(&o).contains("MRFMAP_MAX_MEMORY=\"abc\""), "{}", stderr(&o));
    let o = bin().args(["--max-memory", "1M", "info", s(&data)]).env("MRFMAP_MAX_MEMORY", "abc").output().unwrap();
    assert!(!stderr(&o).contains("MRFMAP_MAX_MEMORY"), "the flag wins: {}", stderr(&o));
    // A voxel larger than the scene: built, with a warning (and no colour codes off a terminal).
    let o = run(&["build", s(&data), "-o", s(&out), "--resolution", "1e9"]);
    let err = stderr(&o);
    assert!(o.status.success() && err.contains("larger than everything the sensors saw"), "{err}");
    assert!(!err.contains('\u{1b}'), "escape codes in {err:?}");
    // Argument errors: exit 1 and the usual prefix, like every other error.
    for args in [vec!["--threads", "100000", "info", s(&out)], vec!["build", s(&data)], vec!["frobnicate"]] {
        let o = run(&args);
        assert_eq!(o.status.code(), Some(1), "{args:?}");
        assert!(stderr(&o).starts_with("mrfmap: error:"), "{args:?}: {}", stderr(&o));
    }
    assert!(run(&["--help"]).status.success());
    // A simulated camera no sensor has, and a noise model with a negative std.
    let scene = dir.join("huge.toml");
    std::fs::write(&scene, SCENE.replace("width = 80", "width = 100000000")).unwrap();
    let o = run(&["simulate", s(&scene), s(&dir.join("huge"))]);
    assert!(!o.status.success() && stderr(&o).contains("larger than any depth sensor"), "{}", stderr(&o));
    assert!(!dir.join("huge").exists(), "nothing left behind");
    let noise = dir.join("noise.toml");
    std::fs::write(&noise, "bias = [0.0]\nstd = [-0.01]\n").unwrap();
    let o = run(&["build", s(&data), "-o", s(&out), "--resolution", "0.05", "--noise", s(&noise), "--engine", "crm"]);
    assert!(
        !o.status.success() && stderr(&o).contains("noise.toml") && stderr(&o).contains("not positive"),
        "{}",
        stderr(&o)
    );
    // Small things: the demo into a file, a zero field of view, eval on a view the map saw.
    let o = run(&["demo", s(&noise)]);
    assert!(!o.status.success() && stderr(&o).contains("not a folder"), "{}", stderr(&o));
    let held = dir.join("held.mrfmap");
    assert!(run(&["build", s(&data), "-o", s(&held), "--resolution", "0.05", "--exclude", "1"]).status.success());
    let o = run(&["view", s(&held), "-o", s(&dir.join("v.png")), "--fov", "0"]);
    assert!(!o.status.success() && stderr(&o).contains("between 0 and 179"), "{}", stderr(&o));
    let o = run(&["eval", s(&held), s(&data), "--views", "0,1"]);
    assert!(o.status.success() && stderr(&o).contains("views [0] were used to build this map"), "{}", stderr(&o));
}

/// Writes a ROS 2 bag of `data` with `tests/bags/make_bag.py` (needs the `rosbags` package:
/// `.ci/run` installs it and names its Python in MRFMAP_ROSBAGS_PYTHON).
fn make_bag(data: &Path, out: &Path, extra: &[&str]) -> bool {
    let Some(python) = std::env::var_os("MRFMAP_ROSBAGS_PYTHON") else {
        eprintln!("skipping the ROS bag checks: MRFMAP_ROSBAGS_PYTHON (a Python with `rosbags`) is not set");
        return false;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bags/make_bag.py");
    let o = Command::new(python).arg(script).arg(data).arg(out).args(extra).output().expect("python runs");
    assert!(o.status.success(), "make_bag.py: {}", String::from_utf8_lossy(&o.stderr));
    true
}

fn same_maps(a: &Path, b: &Path) {
    let (a, b) = (mrfmap::map::Map::load(a).unwrap(), mrfmap::map::Map::load(b).unwrap());
    assert_eq!(a.voxels.len(), b.voxels.len());
    assert!(a.voxels.iter().all(|(k, v)| b.voxels.get(k) == Some(v)), "maps differ");
}

#[test]
fn ros2_bags_build_the_same_map_as_the_dataset() {
    let dir = workdir("bags");
    let data = dataset(&dir);
    let tum = dir.join("tum.mrfmap");
    assert!(run(&["build", s(&data), "-o", s(&tum), "--resolution", "0.05", "-q"]).status.success());
    let direct = dir.join("direct");
    if !make_bag(&data, &direct, &["--direct"]) {
        return;
    }
    let o = run(&["bag", "info", s(&direct)]);
    let info = stdout(&o);
    assert!(info.contains("/camera/depth/image_rect_raw") && info.contains("sensor_msgs/msg/Image"), "{info}");
    assert!(info.contains("TF frames: camera_depth_optical, map") && info.contains("lasts"), "{info}");
    let o = run(&["bag", "info", s(&direct), "--json"]);
    let json: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap();
    let topics = json["topics"].as_array().unwrap();
    let image = topics.iter().find(|t| t["topic"] == "/camera/depth/image_rect_raw").unwrap();
    assert_eq!((image["type"].as_str(), image["messages"].as_u64()), (Some("sensor_msgs/msg/Image"), Some(4)));
    let (start, end) = (json["start"].as_f64().unwrap(), json["end"].as_f64().unwrap());
    assert!(start <= image["first"].as_f64().unwrap() && end >= image["last"].as_f64().unwrap(), "{json}");
    assert!((json["duration"].as_f64().unwrap() - (end - start)).abs() < 1e-9);
    assert_eq!(json["tf_frames"], serde_json::json!(["camera_depth_optical", "map"]));
    let depth = ["--depth-topic", "/camera/depth/image_rect_raw"];
    let build = |bag: &Path, out: &Path, extra: &[&str]| {
        let mut args = vec!["build", s(bag), "-o", s(out), "--resolution", "0.05"];
        args.extend_from_slice(extra);
        run(&args)
    };
    // Poses from /tf, from a /tf + /tf_static chain, and from a pose topic: the same map as
    // the TUM layout of the same data.
    let m = dir.join("bag.mrfmap");
    // Builds from `bag` with the depth topic and `poses`, checks the map is the TUM layout's,
    // and returns the log.
    let same_as_tum = |bag: &Path, poses: &[&str]| {
        let mut args = depth.to_vec();
        args.extend_from_slice(poses);
        let o = build(bag, &m, &args);
        assert!(o.status.success(), "{}", stderr(&o));
        same_maps(&tum, &m);
        stderr(&o)
    };
    same_as_tum(&direct, &["--fixed-frame", "map"]);
    // Read once, its length known only at its end: --exclude as for a dataset, indices beyond
    // the images and maps that cannot fit refused before anything is written.
    let held = dir.join("held.mrfmap");
    assert!(run(&["build", s(&data), "-o", s(&held), "--resolution", "0.05", "--exclude", "2", "-q"]).status.success());
    let o = build(&direct, &m, &[depth[0], depth[1], "--fixed-frame", "map", "--exclude", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    same_maps(&held, &m);
    let refused = dir.join("refused.mrfmap");
    let o = build(&direct, &refused, &[depth[0], depth[1], "--fixed-frame", "map", "--frames", "1,9"]);
    assert!(!o.status.success() && stderr(&o).contains("frame index 9 is out of range"), "{}", stderr(&o));
    let mut args = vec!["--max-memory", "20M", "build", s(&direct), "-o", s(&refused), "--resolution", "0.001"];
    args.extend([depth[0], depth[1], "--fixed-frame", "map"]);
    let o = run(&args);
    assert!(!o.status.success() && stderr(&o).contains("would need about"), "{}", stderr(&o));
    assert!(!refused.exists());
    let chain = dir.join("chain");
    make_bag(&data, &chain, &[]);
    same_as_tum(&chain, &["--fixed-frame", "map"]);
    let file = chain.join("chain.mcap");
    for topic in ["/camera/pose", "/camera/odom", "/camera/transform"] {
        same_as_tum(&file, &["--pose-topic", topic]);
    }
    let sqlite = dir.join("sqlite");
    make_bag(&data, &sqlite, &["--db3"]);
    same_as_tum(&sqlite, &["--fixed-frame", "map"]);
    // `loo`, `eval` and `bench` take the bag too (scored against its own depth images).
    let o = run(&["loo", s(&direct), depth[0], depth[1], "--fixed-frame", "map", "--resolution", "0.05", "--json"]);
    let v: serde_json::Value = serde_json::from_str(&stdout(&o)).unwrap_or_else(|_| panic!("{}", stderr(&o)));
    assert_eq!(v["views"].as_array().unwrap().len(), 4);
    let o = run(&["eval", s(&tum), s(&direct), depth[0], depth[1], "--fixed-frame", "map", "--views", "1", "--json"]);
    assert!(o.status.success() && stdout(&o).contains("\"accuracy\""), "{}", stderr(&o));
    let o = run(&[
        "bench",
        s(&direct),
        depth[0],
        depth[1],
        "--fixed-frame",
        "map",
        "--resolutions",
        "0.1",
        "--repeat",
        "1",
    ]);
    assert!(o.status.success() && stdout(&o).contains("4 frames of"), "{}", stderr(&o));
    // Images logged out of stamp order: a warning naming the topic, the same map.
    let reversed = dir.join("reversed");
    make_bag(&data, &reversed, &["--direct", "--reverse"]);
    let log = same_as_tum(&reversed, &["--fixed-frame", "map"]);
    assert!(log.contains("/camera/depth/image_rect_raw: image 2 is stamped before"), "{log}");
    // A ROS 1 bag of the same data (our ROS 1 reader and ROS 1 serialisation).
    let ros1 = dir.join("ros1.bag");
    make_bag(&data, &ros1, &["--ros1"]);
    same_as_tum(&ros1, &["--fixed-frame", "map"]);
    // Cut short anywhere (a robot that lost power): `bag info` and `build` never panic; they
    // read what is complete and say where the file stops, or fail with a clear error.
    let bytes = std::fs::read(&ros1).unwrap();
    let cut = dir.join("cut.bag");
    for at in (1..20).map(|k| k * bytes.len() / 20).chain([10, 100, 1000]) {
        std::fs::write(&cut, &bytes[..at]).unwrap();
        for o in [run(&["bag", "info", s(&cut)]), build(&cut, &m, &[depth[0], depth[1], "--fixed-frame", "map"])] {
            let err = stderr(&o);
            assert_ne!(o.status.code(), Some(101), "cut at {at}: {err}");
            assert!(!err.contains("panicked"), "cut at {at}: {err}");
            assert!(o.status.success() || err.contains("cut.bag"), "cut at {at}: {err}");
        }
    }
    let o = run(&["bag", "info", s(&cut)]);
    assert!(stderr(&o).contains("cut short") && stderr(&o).contains("byte"), "{}", stderr(&o));
    // A file that is no bag at all: the error alone, no table header before it.
    std::fs::write(dir.join("junk.bag"), b"not a bag").unwrap();
    let o = run(&["bag", "info", s(&dir.join("junk.bag"))]);
    assert!(!o.status.success() && stdout(&o).is_empty() && stderr(&o).contains("junk.bag"), "{}", stderr(&o));
    // compressedDepth images (16UC1 millimetres), PNG or RVL: the same map either way, and
    // within the millimetre rounding of the dataset's.
    let (png, rvl) = (dir.join("png"), dir.join("rvl"));
    make_bag(&data, &png, &["--direct", "--compressed", "png"]);
    make_bag(&data, &rvl, &["--direct", "--compressed", "rvl"]);
    let compressed = ["--depth-topic", "/camera/depth/image_rect_raw/compressedDepth"];
    let info = ["--camera-info-topic", "/camera/depth/camera_info"];
    let (mp, mr) = (dir.join("png.mrfmap"), dir.join("rvl.mrfmap"));
    for (bag, out) in [(&png, &mp), (&rvl, &mr)] {
        let o = build(bag, out, &[compressed[0], compressed[1], info[0], info[1], "--fixed-frame", "map"]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    same_maps(&mp, &mr);
    let (a, b) = (mrfmap::map::Map::load(&mp).unwrap(), mrfmap::map::Map::load(&tum).unwrap());
    let agree = a
        .voxels
        .iter()
        .filter(|(k, v)| b.voxels.get(*k).is_some_and(|w| (w.occupancy > 0.5) == (v.occupancy > 0.5)))
        .count();
    assert!(agree as f64 > 0.99 * b.voxels.len() as f64, "{agree} of {}", b.voxels.len());
    // The bag as a dataset again: the same map.
    let exported = dir.join("exported");
    let o = run(&["export-dataset", s(&direct), "-o", s(&exported), depth[0], depth[1], "--fixed-frame", "map"]);
    assert!(o.status.success() && stdout(&o).contains("4 frames"), "{}", stderr(&o));
    let again = dir.join("again.mrfmap");
    assert!(run(&["build", s(&exported), "-o", s(&again), "--resolution", "0.05", "-q"]).status.success());
    same_maps(&tum, &again);
    // A planar laser in a bag: LaserScan posed by /tf, the CARMEN test's room.
    let scans = dir.join("scans");
    let o = Command::new(std::env::var_os("MRFMAP_ROSBAGS_PYTHON").unwrap())
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bags/make_scan_bag.py"))
        .arg(&scans)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for (engine, topic) in [("logodds", "--scan-topic"), ("crm", "--scan-topic"), ("logodds", "--cloud-topic")] {
        let source = if topic == "--scan-topic" { "/scan" } else { "/points" };
        let o = build(&scans, &m, &[topic, source, "--fixed-frame", "map", "--engine", engine]);
        assert!(o.status.success() && stdout(&o).contains("4 frames"), "{}", stderr(&o));
        let yaml = dir.join(format!("scan-{engine}-{}.yaml", &source[1..]));
        assert!(run(&["export", s(&m), "--grid2d", s(&yaml)]).status.success());
        check_square_room(&yaml, &format!("{engine} from {source}"));
    }
    // Scans are held until the build: more than the memory limit allows is refused.
    let mut args = vec!["--max-memory", "20K", "build", s(&scans), "-o", s(&m), "--resolution", "0.05"];
    args.extend(["--scan-topic", "/scan", "--fixed-frame", "map"]);
    let o = run(&args);
    assert!(!o.status.success() && stderr(&o).contains("scans: holding 3 scans of /scan"), "{}", stderr(&o));
    // What goes wrong says which topic and what.
    let o = build(&direct, &m, &[depth[0], depth[1], "--fixed-frame", "map", "--camera-info-topic", "/nope"]);
    assert!(!o.status.success() && stderr(&o).contains("no CameraInfo on /nope"), "{}", stderr(&o));
    let o = build(&direct, &m, &[depth[0], depth[1], "--fixed-frame", "world"]);
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("does not connect") && err.contains("no image"), "{err}");
    let o = build(&direct, &m, &["--depth-topic", "/camera/pose", info[0], info[1], "--fixed-frame", "map"]);
    assert!(!o.status.success() && stderr(&o).contains("not sensor_msgs/msg/Image"), "{}", stderr(&o));
    let o = build(&direct, &m, &["--fixed-frame", "map"]);
    assert!(!o.status.success() && stderr(&o).contains("--depth-topic"), "{}", stderr(&o));
    let bytes = std::fs::read(direct.join("direct.mcap")).unwrap();
    // An MCAP file cut short: the complete messages before the cut are read, with a warning
    // saying where the file stops; anywhere else, a clear error naming the file, never a panic.
    let cut = dir.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let o = build(&cut, &m, &[depth[0], depth[1], "--fixed-frame", "map"]);
    assert!(o.status.success() && stderr(&o).contains("cut.mcap: cut short at byte"), "{}", stderr(&o));
    for at in (1..12).map(|k| k * bytes.len() / 12) {
        std::fs::write(&cut, &bytes[..at]).unwrap();
        let o = build(&cut, &m, &[depth[0], depth[1], "--fixed-frame", "map"]);
        let err = stderr(&o);
        assert_ne!(o.status.code(), Some(101), "cut at {at}: {err}");
        assert!(o.status.success() || err.contains("cut.mcap"), "cut at {at}: {err}");
    }
}

/// Shell completion scripts name the subcommands and their options; an unknown shell is an
/// argument error.
#[test]
fn shell_completions() {
    for shell in ["bash", "zsh", "fish"] {
        let o = run(&["completions", shell]);
        let script = stdout(&o);
        assert!(o.status.success() && script.contains("mrfmap"), "{shell}: {}", stderr(&o));
        assert!(script.contains("export-dataset") && script.contains("--snapshot-every"), "{shell}");
    }
    let o = run(&["completions", "tcsh"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
}

/// `--snapshot-every` writes the map as it grows, the last snapshot being the map written;
/// `--mcap-timeline` writes one Foxglove scene update per snapshot at increasing log times.
#[test]
fn snapshots_and_their_foxglove_timeline() {
    let dir = workdir("snapshots");
    let data = dataset(&dir);
    let frames =
        std::fs::read_to_string(data.join("depth.txt")).unwrap().lines().filter(|l| !l.starts_with('#')).count();
    let (m, snaps, timeline) = (dir.join("m.mrfmap"), dir.join("snaps"), dir.join("t.mcap"));
    let args = |every: &str| {
        let mut a = vec!["build", s(&data), "-o", s(&m), "--resolution", "0.05", "-q"];
        a.extend(["--snapshot-every", every, s(&snaps), "--mcap-timeline", s(&timeline)]);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let listed = |dir: &Path| {
        let mut names: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        names.sort();
        names
    };
    // Every frame its snapshot.
    let o = run(&args("1e-9").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", stderr(&o));
    let written = listed(&snaps);
    assert_eq!(written.len(), frames, "{written:?}");
    let last = mrfmap::map::Map::load(written.last().unwrap()).unwrap();
    let built = mrfmap::map::Map::load(&m).unwrap();
    assert_eq!(last.voxels.len(), built.voxels.len());
    assert!(built.voxels.iter().all(|(k, v)| last.voxels.get(k) == Some(v)), "the last snapshot is the map");
    let first = mrfmap::map::Map::load(&written[0]).unwrap();
    assert!(first.voxels.len() < last.voxels.len(), "the map grows");
    let bytes = std::fs::read(&timeline).unwrap();
    let times: Vec<u64> = mcap::MessageStream::new(&bytes).unwrap().map(|m| m.unwrap().log_time).collect();
    assert_eq!(times.len(), frames);
    assert!(times.windows(2).all(|w| w[0] < w[1]), "{times:?}");
    // One after the first frame, and the last frame's.
    std::fs::remove_dir_all(&snaps).unwrap();
    let o = run(&args("1e9").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(listed(&snaps).len(), 2);
    // Refused before any work: a bad interval, the batch MRF, laser logs.
    let o = run(&args("-1").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!o.status.success() && stderr(&o).contains("positive number of seconds"), "{}", stderr(&o));
    let mut mrf = args("1");
    mrf.extend(["--engine".into(), "mrf".into()]);
    let o = run(&mrf.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!o.status.success() && stderr(&o).contains("--online"), "{}", stderr(&o));
    // (Same data:) an MRF build that stops at its sweep cap says whether that matters.
    let capped = ["--engine", "mrf", "--tolerance", "1e-12", "--iterations", "1"];
    let o = run(&[&["build", s(&data), "-o", s(&m), "--resolution", "0.05"][..], &capped[..]].concat());
    let err = stderr(&o);
    assert!(o.status.success() && err.contains("not converged within the 1 sweeps --iterations allows"), "{err}");
    assert!(err.contains("held-out accuracy does not need convergence"), "{err}");
}

/// Both metrics in one run, the biased target, the reference protocol in `loo` and `compare`,
/// and the log-odds clamp: reported where a script reads them, bad values refused.
#[test]
fn protocols_targets_metrics_and_clamp() {
    let dir = workdir("protocols");
    let map = logodds_map(&dir);
    let data = dir.join("data");
    let o = run(&["eval", s(&map), s(&data), "--views", "1", "--metric", "algorithms,reference", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json = stdout(&o);
    assert!(
        json.contains("\"metrics\": {\"algorithms\": {\"accuracy\"") && json.contains("\"reference\": {"),
        "{json}"
    );
    // The biased target scores the same pixels (valid + invalid) against other depths.
    let counts = |json: &str| -> usize {
        ["\"valid\": ", "\"invalid\": "]
            .iter()
            .map(|k| json.split(k).nth(1).unwrap().split([',', '}']).next().unwrap().parse::<usize>().unwrap())
            .sum()
    };
    let truth = stdout(&run(&["eval", s(&map), s(&data), "--views", "1", "--json"]));
    let o = run(&["eval", s(&map), s(&data), "--views", "1", "--target", "biased", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(counts(&stdout(&o)), counts(&truth), "{} vs {truth}", stdout(&o));

    let o = run(&["loo", s(&data), "--resolution", "0.1", "--views", "0", "--protocol", "reference", "--json", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("\"protocol\": \"reference\"") && stdout(&o).contains("\"accuracy\""),
        "{}",
        stdout(&o)
    );
    let report = dir.join("report");
    let o = run(&[
        "compare",
        s(&data),
        "--resolutions",
        "0.1",
        "--views",
        "1",
        "--protocol",
        "truth,reference",
        "--metric",
        "algorithms,reference",
        "-o",
        s(&report),
        "-q",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let md = std::fs::read_to_string(report.join("report.md")).unwrap();
    for heading in ["truth protocol, algorithms metric", "reference protocol, reference metric"] {
        assert!(md.contains(heading), "no {heading:?} in {md}");
    }
    assert!(report.join("reference_logodds_0.1_view1_accuracy.png").is_file());
    assert!(md.contains("--protocol truth,reference"), "{md}");

    build_fails(&data, &["--clamp", "0.9,0.1"], &["clamp", "0 < MIN < MAX < 1"]);
    // The model's std (2-10 mm here) as the tolerance is stricter than 5 cm: fewer accurate.
    let accurate = |json: &str| -> usize {
        json.split("\"accurate\": ").nth(1).unwrap().split(',').next().unwrap().parse().unwrap()
    };
    let o = run(&["eval", s(&map), s(&data), "--views", "1", "--sigma-model", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(accurate(&stdout(&o)) < accurate(&truth), "{} vs {truth}", stdout(&o));
    // Without a noise model there is no bias to add and no std to judge by.
    std::fs::remove_file(data.join("noise.toml")).unwrap();
    let o = run(&["eval", s(&map), s(&data), "--views", "1", "--target", "biased"]);
    assert!(!o.status.success() && stderr(&o).contains("noise.toml"), "{}", stderr(&o));
    let o = run(&["eval", s(&map), s(&data), "--views", "1", "--sigma-model"]);
    assert!(!o.status.success() && stderr(&o).contains("--sigma-model needs a noise model"), "{}", stderr(&o));
}

/// `build --online`: the frames fed in order on the MRF's online schedule, one timings row per
/// keyframe within the tile budget, the backlog written down, and a map that `--finish`
/// settles; the options only where they mean something.
#[test]
fn mrf_online_build_writes_timings_and_honours_the_budget() {
    let dir = workdir("mrf-online");
    let data = dataset(&dir);
    let (map, timings) = (dir.join("online.mrfmap"), dir.join("t.csv"));
    let base = ["build", s(&data), "-o", s(&map), "--resolution", "0.05", "--engine", "mrf", "--online"];
    let o = run(&[&base[..], &["--budget-tiles", "25", "--timings", s(&timings), "-q"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(&timings).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(csv.lines().next(), Some("keyframe,ms,traced_tiles,backlog_tiles"));
    assert_eq!(rows.len(), 4, "{csv}");
    for (n, row) in rows.iter().enumerate() {
        assert_eq!(row[0], (n + 1).to_string());
        assert!(row[1].parse::<f64>().unwrap() > 0.0, "{csv}");
        // 80x60 pixels: 20 own tiles, at most 25 in all.
        let traced: usize = row[2].parse().unwrap();
        assert!((20..=25).contains(&traced), "{csv}");
    }
    assert!(rows[3][3].parse::<usize>().unwrap() > 0, "a 5-tile budget leaves a backlog: {csv}");
    let online = mrfmap::map::Map::load(&map).unwrap();
    assert!(online.occupied_count() > 0);
    // --finish infers the rest before writing; the map differs from the unfinished one.
    let finished = dir.join("finished.mrfmap");
    let o = run(&[&base[..2], &["-o", s(&finished)], &base[4..], &["--budget-tiles", "25", "--finish", "-q"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let finished = mrfmap::map::Map::load(&finished).unwrap();
    let differ = online.voxels.iter().filter(|(k, v)| finished.voxels.get(*k) != Some(v)).count();
    assert!(differ > 0);
    build_fails(&data, &["--budget-ms", "10"], &["--online"]);
    build_fails(&data, &["--online"], &["--engine mrf"]);
    build_fails(&data, &["--engine", "mrf", "--online", "--budget-ms=-5"], &["budget-ms"]);
    build_fails(
        &data,
        &["--engine", "mrf", "--online", "--timings", s(&dir.join("no/such/t.csv"))],
        &["output folder"],
    );
}

/// An occupancy threshold outside [0, 1) would select no voxel and write an empty picture,
/// grid or scene: refused, naming the argument; so is a box that is not finite.
#[test]
fn thresholds_and_boxes_outside_their_range_are_refused() {
    let dir = workdir("thresholds");
    let data = dataset(&dir);
    let map = dir.join("m.mrfmap");
    assert!(run(&["build", s(&data), "-o", s(&map), "--resolution", "0.1", "-q"]).status.success());
    let png = dir.join("v.png");
    for args in [
        vec!["view", s(&map), "-o", s(&png), "--threshold", "2"],
        vec!["export", s(&map), "--mcap", s(&dir.join("s.mcap")), "--threshold", "1"],
        vec!["project", s(&map), "--z-min", "0", "--z-max", "1", "-o", s(&dir.join("g.yaml")), "--threshold=-0.1"],
    ] {
        let o = run(&args);
        assert!(
            !o.status.success() && stderr(&o).contains("--threshold") && stderr(&o).contains("[0, 1)"),
            "{args:?}: {}",
            stderr(&o)
        );
    }
    assert!(!png.exists());
    build_fails(&data, &["--bounds=-inf,0,0,1,1,1"], &["bounds", "finite"]);
    // A swapped output flag is found by its extension, before anything is written; a missing
    // folder is named.
    let ply = dir.join("x.ply");
    let o = run(&["export", s(&map), "--ply", s(&ply), "--bt", s(&dir.join("y.ply"))]);
    assert!(
        !o.status.success() && stderr(&o).contains("--bt") && stderr(&o).contains("expected a .bt file"),
        "{}",
        stderr(&o)
    );
    assert!(!ply.exists());
    let o = run(&["export", s(&map), "--ply", s(&dir.join("no/such/x.ply"))]);
    assert!(!o.status.success() && stderr(&o).contains("output folder"), "{}", stderr(&o));
    assert!(run(&["export", s(&map), "--ot", s(&dir.join("x.OT"))]).status.success());
    let o = run(&["view", s(&map), "-o", s(&dir.join("no/such/v.png"))]);
    assert!(!o.status.success() && stderr(&o).contains("output folder"), "{}", stderr(&o));
}

#[test]
fn tiled_maps_equal_the_whole_map_and_are_read_lazily() {
    let dir = workdir("tiles");
    let whole = logodds_map(&dir);
    let data = dir.join("data");
    // Tiles of one brick (0.4 m): over a hundred of them for the 4 m room.
    let tiled = dir.join("tiled");
    let o = run(&["build", s(&data), "-o", s(&tiled), "--resolution", "0.05", "--tile", "0.4", "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(tiled.join("tiles.toml").is_file());
    same_maps(&whole, &tiled);
    let o = run(&["info", s(&tiled), "--json"]);
    let info: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let tiles = info["tiles"].as_u64().unwrap();
    assert!(tiles >= 100, "{tiles} tiles");
    let whole_map = mrfmap::map::Map::load(&whole).unwrap();
    assert_eq!(info["voxels"].as_u64().unwrap(), whole_map.voxels.len() as u64);
    // A 1 m segment along x crosses three tiles of 0.4 m: at most those are read.
    let segment = ["--segment", "0.01,0.1,0.05:1.01,0.1,0.05"];
    let o = run(&[&["query", s(&tiled), "--json"][..], &segment[..]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let read: u64 = stderr(&o).split("read ").nth(1).and_then(|t| t.split(' ').next()?.parse().ok()).expect("read N");
    assert!((1..=3).contains(&read), "{}", stderr(&o));
    let plain = run(&[&["query", s(&whole), "--json"][..], &segment[..]].concat());
    assert_eq!(stdout(&o), stdout(&plain), "the same answer as the whole map");
    // crop reads the tiles its box overlaps and gives the whole map's crop.
    let (a, b) = (dir.join("a.mrfmap"), dir.join("b.mrfmap"));
    for (map, out) in [(&whole, &a), (&tiled, &b)] {
        let o = run(&["crop", s(map), "--box", "-0.5,-0.5,0,0.7,0.5,1", "-o", s(out)]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    same_maps(&a, &b);
    // Bad tiles: not whole bricks, a file where the folder goes, a laser log.
    let o = run(&["build", s(&data), "-o", s(&dir.join("t2")), "--resolution", "0.05", "--tile", "0.3"]);
    assert!(stderr(&o).contains("whole number of bricks") && stderr(&o).contains("0.4"), "{}", stderr(&o));
    let o = run(&["build", s(&data), "-o", s(&whole), "--resolution", "0.05", "--tile", "0.4"]);
    assert!(stderr(&o).contains("is a file"), "{}", stderr(&o));
    let o =
        run(&["build", s(&data.join("depth.txt")), "-o", s(&dir.join("t3")), "--resolution", "0.05", "--tile", "0.4"]);
    assert!(!o.status.success() && stderr(&o).contains("dataset folder"), "{}", stderr(&o));
    // A tile file gone: the error names it.
    let first = std::fs::read_dir(&tiled).unwrap().flatten().find(|e| e.file_name() != "tiles.toml").unwrap();
    std::fs::remove_file(first.path()).unwrap();
    let o = run(&["export", s(&tiled), "--ply", s(&dir.join("t.ply"))]);
    assert!(!o.status.success() && stderr(&o).contains(first.file_name().to_str().unwrap()), "{}", stderr(&o));
}

/// The CRM engine against the CRM paper's per-ray update written again from the paper alone,
/// in numpy (`bench/crm_column.py`): one column of voxels, a wall read 12 times with 0.13 m
/// noise, the engine's two documented departures done the same way in the script. Every
/// voxel's mean agrees within 1e-3 and both leave the same voxels unknown. (Needs a Python
/// with numpy: `.ci/run` installs one beside `rosbags` and names it in MRFMAP_ROSBAGS_PYTHON.)
#[test]
fn crm_engine_equals_the_papers_update_written_again() {
    let Some(python) = std::env::var_os("MRFMAP_ROSBAGS_PYTHON") else {
        eprintln!("skipping the CRM column check: MRFMAP_ROSBAGS_PYTHON (a Python with numpy) is not set");
        return;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../bench/crm_column.py");
    let args = ["--mrfmap", env!("CARGO_BIN_EXE_mrfmap"), "--rays", "12", "--resolutions", "0.05,0.01"];
    let o = Command::new(python).arg(script).args(args).output().expect("python runs");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "crm_column.py: {}", String::from_utf8_lossy(&o.stderr));
    let worst: f64 = out
        .lines()
        .find_map(|l| l.strip_prefix("largest difference between the two implementations' means: "))
        .unwrap_or_else(|| panic!("no comparison in\n{out}"))
        .parse()
        .unwrap();
    assert!(worst < 1e-3, "{out}");
    assert_eq!(out.matches("the same voxels as here").count(), 2, "{out}");
}
