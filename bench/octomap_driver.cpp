// OctoMap peer for `bench/peers.sh`: inserts a dataset's depth frames (the layout of
// ALGORITHMS.md section 2) with OcTree::insertPointCloud, OctoMap defaults, no max range,
// and reports the time per frame (insertion only; PNG decoding is not timed) and the
// number of occupied voxels at the finest resolution (pruned leaves expanded).
//
// usage: octomap_driver DATASET RESOLUTION [REPEAT [OUT.bt|- [MAX_RANGE]]]
//   OUT.bt: also write OctoMap's map ("-": none); MAX_RANGE: insertPointCloud's maxrange in
//   metres (default -1, none; OctoMap cuts the ray there and marks no end voxel)
#include <octomap/octomap.h>
#include <png.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

struct Frame {
  std::vector<uint16_t> depth;
  double t[3], q[4];  // qx qy qz qw
};

static std::map<std::string, double> read_camera(const std::string& path) {
  std::map<std::string, double> kv;
  std::ifstream f(path);
  std::string line;
  while (std::getline(f, line)) {
    auto eq = line.find('=');
    if (line.empty() || line[0] == '#' || eq == std::string::npos) continue;
    std::string k = line.substr(0, eq);
    k.erase(k.find_last_not_of(" \t") + 1);
    kv[k] = std::stod(line.substr(eq + 1));
  }
  return kv;
}

static std::vector<std::vector<std::string>> read_table(const std::string& path) {
  std::vector<std::vector<std::string>> rows;
  std::ifstream f(path);
  std::string line;
  while (std::getline(f, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream s(line);
    std::vector<std::string> r;
    std::string w;
    while (s >> w) r.push_back(w);
    if (!r.empty()) rows.push_back(r);
  }
  return rows;
}

static std::vector<uint16_t> read_png16(const std::string& path, int w, int h) {
  png_image img{};
  img.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&img, path.c_str())) {
    std::cerr << path << ": " << img.message << "\n";
    exit(1);
  }
  img.format = PNG_FORMAT_LINEAR_Y;  // 16-bit grey, native byte order, no gamma change
  std::vector<uint16_t> buf(PNG_IMAGE_SIZE(img) / 2);
  if ((int)img.width != w || (int)img.height != h || !png_image_finish_read(&img, nullptr, buf.data(), 0, nullptr)) {
    std::cerr << path << ": cannot read as " << w << "x" << h << " 16-bit PNG\n";
    exit(1);
  }
  return buf;
}

int main(int argc, char** argv) {
  if (argc < 3) {
    std::cerr << "usage: octomap_driver DATASET RESOLUTION [REPEAT [OUT.bt|- [MAX_RANGE]]]\n";
    return 2;
  }
  std::string root = argv[1];
  double res = std::stod(argv[2]);
  int repeat = argc > 3 ? std::stoi(argv[3]) : 1;
  std::string out = argc > 4 ? argv[4] : "-";
  double max_range = argc > 5 ? std::stod(argv[5]) : -1.0;
  auto cam = read_camera(root + "/camera.toml");
  int w = (int)cam["width"], h = (int)cam["height"];
  double fx = cam["fx"], fy = cam["fy"], cx = cam["cx"], cy = cam["cy"], scale = cam["depth_scale"];
  // Frames and poses share timestamps in our datasets (nearest match within 0.02 s).
  auto depths = read_table(root + "/depth.txt");
  auto poses = read_table(root + "/groundtruth.txt");
  std::vector<Frame> frames;
  for (auto& d : depths) {
    double td = std::stod(d[0]);
    for (auto& p : poses) {
      if (std::fabs(std::stod(p[0]) - td) <= 0.02) {
        Frame f;
        f.depth = read_png16(root + "/" + d[1], w, h);
        for (int i = 0; i < 3; i++) f.t[i] = std::stod(p[1 + i]);
        for (int i = 0; i < 4; i++) f.q[i] = std::stod(p[4 + i]);
        frames.push_back(std::move(f));
        break;
      }
    }
  }
  // Point clouds in the world frame, built before timing.
  std::vector<octomap::Pointcloud> clouds(frames.size());
  std::vector<octomap::point3d> origins;
  for (size_t k = 0; k < frames.size(); k++) {
    auto& f = frames[k];
    octomath::Quaternion q(f.q[3], f.q[0], f.q[1], f.q[2]);
    octomap::pose6d pose(octomath::Vector3(f.t[0], f.t[1], f.t[2]), q);
    for (int v = 0; v < h; v++)
      for (int u = 0; u < w; u++) {
        uint16_t raw = f.depth[v * w + u];
        if (!raw) continue;
        double z = raw / scale;
        clouds[k].push_back(pose.transform(octomap::point3d((u - cx) / fx * z, (v - cy) / fy * z, z)));
      }
    origins.push_back(octomap::point3d(f.t[0], f.t[1], f.t[2]));
  }
  double best = 1e300;
  size_t occupied = 0, leaves = 0;
  octomap::OcTree tree(res);
  for (int r = 0; r < repeat; r++) {
    tree.clear();
    auto t0 = std::chrono::steady_clock::now();
    for (size_t k = 0; k < clouds.size(); k++) tree.insertPointCloud(clouds[k], origins[k], max_range);
    double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    best = std::min(best, secs);
    occupied = leaves = 0;
    for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
      if (tree.isNodeOccupied(*it)) {
        leaves++;
        size_t side = (size_t)1 << (tree.getTreeDepth() - it.getDepth());
        occupied += side * side * side;
      }
    }
  }
  std::printf("%g\t%.2f\t%zu\t%zu\n", res, best * 1e3 / clouds.size(), occupied, leaves);
  // Optionally OctoMap's own map of the frames, for comparing exported files.
  if (out != "-" && !tree.writeBinary(out)) {
    std::cerr << "cannot write " << out << "\n";
    return 1;
  }
  return 0;
}
