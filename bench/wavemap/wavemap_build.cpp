// wavemap_build DATASET --cell-width W [options] : integrates every depth frame of a TUM-layout
// dataset (camera.toml, depth.txt, groundtruth.txt; layout of docs/ALGORITHMS.md section 2) into a wavemap
// (ethz-asl/wavemap, RSS 2023) occupancy map, built without ROS, and prints one summary line.
//
// Settings follow wavemap's own depth-camera example config
// (interfaces/ros1/wavemap_ros/config/wavemap_panoptic_mapping_rgbd.yaml): map
// hashed_chunked_wavelet_octree (the docs' "best performance" data structure; --map hashed gives
// hashed_wavelet_octree + hashed_wavelet_integrator), pinhole_camera_projector, continuous_ray
// measurement model (scaling_free 0.2, scaling_occupied 0.4), hashed_chunked_wavelet_integrator
// (projective, coarse-to-fine), min_range 0.1 m; map log-odds clamped to wavemap's defaults
// [-2, 4] by a threshold() after every frame (the example runs threshold_map every 2 s).
// range_sigma defaults to max(cell/2, 0.01 m), the rule stated in wavemap's LiDAR example configs
// ("we recommend setting range_sigma to max(min_cell_width / 2, sensor_noise)"); the RGBD
// example's 0.01 m equals it at 0.02 m cells.
//
// Options: --max-range M (default 6; 0 = none, i.e. 1000 m), --min-range M (0.1),
//   --range-sigma M, --map chunked|hashed, --threads N (wavemap ThreadPool; default all cores),
//   --ply OUT.ply (occupied cells expanded to finest-resolution cell centres, binary PLY),
//   --wvmp OUT.wvmp (wavemap's own map file), --per-frame (print each frame's time).
// Negative fx / fy (e.g. ICL-NUIM's fy = -480): wavemap's projector requires fx, fy > 0, so the
//   image is mirrored on that axis and the principal point moved to (W-1)-cx / (H-1)-cy, which
//   keeps every pixel's camera-frame ray (x right, y down, z forward) unchanged.
// Timing: seconds_per_frame and total_seconds cover integrate() + threshold() only (not PNG
//   decoding, pose parsing, nor conversion of uint16 to a float image); threshold_seconds is the
//   threshold() share of total_seconds; the final prune() is timed separately. peak_rss_mb is getrusage(RUSAGE_SELF).ru_maxrss of the whole process.
// Occupied: wavemap's OccupancyClassifier with its default threshold, i.e. log-odds >= 0 and
//   |log-odds| > 1e-3 (wavemap's "unobserved" band); a leaf at height h counts 8^h finest cells.
//
// Build: see build_wavemap.sh next to this file.
#include <png.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <wavemap/core/common.h>
#include <wavemap/core/data_structure/image.h>
#include <wavemap/core/indexing/index_conversions.h>
#include <wavemap/core/integrator/measurement_model/continuous_ray.h>
#include <wavemap/core/integrator/projection_model/pinhole_camera_projector.h>
#include <wavemap/core/integrator/projective/coarse_to_fine/hashed_chunked_wavelet_integrator.h>
#include <wavemap/core/integrator/projective/coarse_to_fine/hashed_wavelet_integrator.h>
#include <wavemap/core/map/hashed_chunked_wavelet_octree.h>
#include <wavemap/core/map/hashed_wavelet_octree.h>
#include <wavemap/core/utils/thread_pool.h>
#include <wavemap/io/file_conversions.h>

using namespace wavemap;  // NOLINT

namespace {
[[noreturn]] void die(const std::string& msg) {
  std::fprintf(stderr, "wavemap_build: %s\n", msg.c_str());
  std::exit(2);
}

std::map<std::string, double> readCameraToml(const std::string& path) {
  std::ifstream in(path);
  if (!in) die("cannot open " + path);
  std::map<std::string, double> kv;
  std::string line;
  while (std::getline(in, line)) {
    if (auto hash = line.find('#'); hash != std::string::npos) line.resize(hash);
    auto eq = line.find('=');
    if (eq == std::string::npos) continue;
    auto trim = [](std::string s) {
      s.erase(0, s.find_first_not_of(" \t\r\""));
      s.erase(s.find_last_not_of(" \t\r\"") + 1);
      return s;
    };
    kv[trim(line.substr(0, eq))] = std::atof(trim(line.substr(eq + 1)).c_str());
  }
  for (const char* k : {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"})
    if (!kv.count(k)) die(path + " lacks " + k);
  return kv;
}

// Lines "t a b c ..." (comments '#' skipped), sorted by t.
std::vector<std::vector<std::string>> readTable(const std::string& path) {
  std::ifstream in(path);
  if (!in) die("cannot open " + path);
  std::vector<std::vector<std::string>> rows;
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ss(line);
    std::vector<std::string> row;
    for (std::string tok; ss >> tok;) row.push_back(tok);
    if (!row.empty()) rows.push_back(row);
  }
  std::stable_sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) {
    return std::atof(a[0].c_str()) < std::atof(b[0].c_str());
  });
  return rows;
}

// 16-bit (or 8-bit) grayscale PNG -> row-major uint16 values.
std::vector<uint16_t> readPng16(const std::string& path, int& w, int& h) {
  FILE* f = std::fopen(path.c_str(), "rb");
  if (!f) die("cannot open " + path);
  png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png_create_info_struct(png);
  if (setjmp(png_jmpbuf(png))) die("libpng error reading " + path);
  png_init_io(png, f);
  png_read_info(png, info);
  w = png_get_image_width(png, info);
  h = png_get_image_height(png, info);
  const int depth = png_get_bit_depth(png, info);
  const int color = png_get_color_type(png, info);
  if (color != PNG_COLOR_TYPE_GRAY) die(path + ": not a grayscale PNG");
  if (depth < 8) png_set_expand_gray_1_2_4_to_8(png);
  if (depth == 16) png_set_swap(png);  // PNG is big-endian
  png_read_update_info(png, info);
  const size_t rowbytes = png_get_rowbytes(png, info);
  std::vector<uint8_t> buf(rowbytes * h);
  std::vector<png_bytep> rows(h);
  for (int v = 0; v < h; ++v) rows[v] = buf.data() + v * rowbytes;
  png_read_image(png, rows.data());
  png_destroy_read_struct(&png, &info, nullptr);
  std::fclose(f);
  std::vector<uint16_t> out(size_t(w) * h);
  if (depth == 16)
    std::memcpy(out.data(), buf.data(), out.size() * 2);
  else
    for (size_t i = 0; i < out.size(); ++i) out[i] = buf[i];
  return out;
}

double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}
}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || argv[1][0] == '-') {
    std::fprintf(stderr,
                 "usage: wavemap_build DATASET --cell-width W [--max-range 6] [--min-range 0.1] "
                 "[--range-sigma S] [--map chunked|hashed] [--threads N] [--ply OUT.ply] "
                 "[--wvmp OUT.wvmp] [--per-frame]\n");
    return 2;
  }
  const double t_start = now();
  const std::string ds = argv[1];
  double cell = 0, max_range = 6.0, min_range = 0.1, range_sigma = -1;
  std::string map_kind = "chunked", ply_path, wvmp_path;
  size_t threads = std::max(1u, std::thread::hardware_concurrency());
  bool per_frame = false;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) die("missing value after " + a);
      return argv[++i];
    };
    if (a == "--cell-width" || a == "--resolution") cell = std::atof(next().c_str());
    else if (a == "--max-range") max_range = std::atof(next().c_str());
    else if (a == "--min-range") min_range = std::atof(next().c_str());
    else if (a == "--range-sigma") range_sigma = std::atof(next().c_str());
    else if (a == "--map") map_kind = next();
    else if (a == "--threads") threads = std::atoi(next().c_str());
    else if (a == "--ply") ply_path = next();
    else if (a == "--wvmp") wvmp_path = next();
    else if (a == "--per-frame") per_frame = true;
    else die("unknown option " + a);
  }
  if (!(cell > 0)) die("--cell-width must be > 0");
  if (max_range <= 0) max_range = 1000.0;  // "none"
  if (range_sigma <= 0) range_sigma = std::max(cell / 2, 0.01);
  if (map_kind != "chunked" && map_kind != "hashed") die("--map chunked|hashed");

  // Camera, with negative focal lengths turned into mirrored images.
  auto cam = readCameraToml(ds + "/camera.toml");
  const int W = int(cam["width"]), H = int(cam["height"]);
  const bool flip_u = cam["fx"] < 0, flip_v = cam["fy"] < 0;
  const double fx = std::abs(cam["fx"]), fy = std::abs(cam["fy"]);
  const double cx = flip_u ? (W - 1) - cam["cx"] : cam["cx"];
  const double cy = flip_v ? (H - 1) - cam["cy"] : cam["cy"];
  const double depth_scale = cam["depth_scale"];

  // Depth frames and nearest-timestamp poses.
  auto depth_rows = readTable(ds + "/depth.txt");
  auto pose_rows = readTable(ds + "/groundtruth.txt");
  if (depth_rows.empty() || pose_rows.empty()) die("empty depth.txt or groundtruth.txt");

  // Map and integrator (what IntegratorFactory builds from the example YAML).
  PinholeCameraProjectorConfig proj_cfg{float(fx), float(fy), float(cx), float(cy), H, W};
  auto projector = std::make_shared<PinholeCameraProjector>(proj_cfg);
  auto posed_range_image = std::make_shared<PosedImage<>>(projector->getDimensions());
  auto beam_offset_image = std::make_shared<Image<Vector2D>>(projector->getDimensions());
  ContinuousRayConfig ray_cfg{float(range_sigma), 0.2f, 0.4f};
  auto meas_model = std::make_shared<ContinuousRay>(ray_cfg, projector, posed_range_image);
  ProjectiveIntegratorConfig integ_cfg{float(min_range), float(max_range)};
  auto pool = std::make_shared<ThreadPool>(threads);
  MapBase::Ptr map;
  std::unique_ptr<IntegratorBase> integrator;
  if (map_kind == "chunked") {
    HashedChunkedWaveletOctreeConfig mcfg;
    mcfg.min_cell_width = float(cell);
    auto m = std::make_shared<HashedChunkedWaveletOctree>(mcfg);
    integrator = std::make_unique<HashedChunkedWaveletIntegrator>(
        integ_cfg, projector, posed_range_image, beam_offset_image, meas_model, m, pool);
    map = m;
  } else {
    HashedWaveletOctreeConfig mcfg;
    mcfg.min_cell_width = float(cell);
    auto m = std::make_shared<HashedWaveletOctree>(mcfg);
    integrator = std::make_unique<HashedWaveletIntegrator>(
        integ_cfg, projector, posed_range_image, beam_offset_image, meas_model, m, pool);
    map = m;
  }

  std::vector<double> frame_secs;
  double threshold_total = 0;
  size_t valid_pixels = 0;
  float max_depth = 0;
  for (const auto& drow : depth_rows) {
    if (drow.size() < 2) continue;
    const double t = std::atof(drow[0].c_str());
    const std::vector<std::string>* best = nullptr;
    double best_dt = 1e300;
    for (const auto& p : pose_rows) {
      if (p.size() < 8) continue;
      const double dt = std::abs(std::atof(p[0].c_str()) - t);
      if (dt < best_dt) best_dt = dt, best = &p;
    }
    if (!best) die("no pose");
    const auto& p = *best;
    auto d = [&](int k) { return std::atof(p[k].c_str()); };
    Eigen::Quaternionf q(float(d(7)), float(d(4)), float(d(5)), float(d(6)));  // w x y z
    q.normalize();
    Transformation3D T_W_C(Rotation3D(q), Vector3D(float(d(1)), float(d(2)), float(d(3))));

    int w = 0, h = 0;
    auto raw = readPng16(ds + "/" + drow[1], w, h);
    if (w != W || h != H) die(drow[1] + ": image size differs from camera.toml");
    PosedImage<> image(T_W_C, projector->getDimensions());  // indexed (u, v)
    for (int v = 0; v < H; ++v)
      for (int u = 0; u < W; ++u) {
        const uint16_t z = raw[size_t(v) * W + u];
        const float zm = z ? float(z / depth_scale) : 0.f;
        if (z) ++valid_pixels, max_depth = std::max(max_depth, zm);
        image.at({flip_u ? W - 1 - u : u, flip_v ? H - 1 - v : v}) = zm;
      }

    const double t0 = now();
    integrator->integrate(image);
    const double t1 = now();
    map->threshold();
    const double dt = now() - t0;
    threshold_total += now() - t1;
    frame_secs.push_back(dt);
    if (per_frame) std::printf("frame %zu %.4f s\n", frame_secs.size() - 1, dt);
  }
  const double t_p = now();
  map->prune();
  const double prune_s = now() - t_p;

  // Occupied cells at the finest resolution, and optional PLY of their centres.
  constexpr float kUnobserved = 1e-3f;  // OccupancyClassifier::getUnobservedThreshold()
  size_t occ_cells = 0, occ_leaves = 0, free_cells = 0;
  std::vector<float> pts;
  map->forEachLeaf([&](const OctreeIndex& idx, FloatingPoint value) {
    if (std::abs(value) <= kUnobserved) return;
    const size_t n = size_t(1) << (3 * idx.height);
    if (value < 0.f) {
      free_cells += n;
      return;
    }
    occ_cells += n, ++occ_leaves;
    if (ply_path.empty()) return;
    const IndexElement s = IndexElement(1) << idx.height;
    const Index3D base = idx.position * s;
    for (IndexElement a = 0; a < s; ++a)
      for (IndexElement b = 0; b < s; ++b)
        for (IndexElement c = 0; c < s; ++c) {
          const Point3D pc = convert::indexToCenterPoint<3>(base + Index3D(a, b, c), float(cell));
          pts.insert(pts.end(), {pc.x(), pc.y(), pc.z()});
        }
  });
  if (!ply_path.empty()) {
    FILE* o = std::fopen(ply_path.c_str(), "wb");
    if (!o) die("cannot write " + ply_path);
    std::fprintf(o,
                 "ply\nformat binary_little_endian 1.0\ncomment wavemap occupied cells, "
                 "resolution %g\nelement vertex %zu\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n",
                 cell, pts.size() / 3);
    std::fwrite(pts.data(), 4, pts.size(), o);
    std::fclose(o);
  }
  if (!wvmp_path.empty()) io::mapToFile(*map, wvmp_path);

  double total = 0;
  for (double s : frame_secs) total += s;
  std::vector<double> sorted = frame_secs;
  std::sort(sorted.begin(), sorted.end());
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  std::printf(
      "map=%s cell=%g frames=%zu seconds_per_frame=%.5f min_frame=%.5f max_frame=%.5f "
      "total_seconds=%.4f threshold_seconds=%.4f prune_seconds=%.4f occupied_cells=%zu occupied_leaves=%zu "
      "free_cells=%zu map_memory_mb=%.2f peak_rss_mb=%.1f process_seconds=%.4f threads=%zu "
      "range_sigma=%g min_range=%g max_range=%g flip_u=%d flip_v=%d valid_pixels=%zu "
      "max_depth=%.3f\n",
      map_kind.c_str(), cell, frame_secs.size(), total / frame_secs.size(), sorted.front(),
      sorted.back(), total, threshold_total, prune_s, occ_cells, occ_leaves, free_cells,
      map->getMemoryUsage() / 1048576.0, ru.ru_maxrss / 1024.0, now() - t_start, threads,
      range_sigma, min_range, max_range, int(flip_u), int(flip_v), valid_pixels, max_depth);
  return 0;
}
