// PCL keypoint peer for benchmarks/saliency.py: ISS 3D and Harris 3D on a point file.
//
// usage: pcl_keypoints iss|harris INPUT.xyz|INPUT.ply OUTPUT.txt
// Reads points (an "x y z" text file, or a PLY), detects keypoints, writes the indices of the input points
// nearest to them (one per line, sorted, unique) to OUTPUT, and prints the detection time in seconds
// (file I/O excluded) as the last word on stdout.
// Radii follow Open3D's ISS defaults so the two are comparable: resolution = mean nearest-neighbour
// distance; ISS salient radius 6 x resolution, non-maximum radius 4 x, thresholds 0.975, min 5 neighbours.
// Harris 3D uses the salient radius with non-maximum suppression.

#include <pcl/io/ply_io.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/keypoints/harris_3d.h>
#include <pcl/keypoints/iss_3d.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <set>
#include <sstream>
#include <string>

using Cloud = pcl::PointCloud<pcl::PointXYZ>;

static bool read_points(const std::string& path, Cloud& cloud) {
  if (path.size() > 4 && path.substr(path.size() - 4) == ".ply") {
    return pcl::io::loadPLYFile(path, cloud) == 0;
  }
  std::ifstream in(path);
  if (!in) return false;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream row(line);
    pcl::PointXYZ p;
    if (row >> p.x >> p.y >> p.z) cloud.push_back(p);
  }
  return !cloud.empty();
}

static double resolution(const Cloud::ConstPtr& cloud) {
  pcl::KdTreeFLANN<pcl::PointXYZ> tree;
  tree.setInputCloud(cloud);
  std::vector<int> index(2);
  std::vector<float> sq(2);
  double total = 0.0;
  int count = 0;
  for (const auto& p : cloud->points) {
    if (tree.nearestKSearch(p, 2, index, sq) == 2) {
      total += std::sqrt(sq[1]);
      ++count;
    }
  }
  return count ? total / count : 0.0;
}

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: " << argv[0] << " iss|harris INPUT.xyz|INPUT.ply OUTPUT.txt\n";
    return 2;
  }
  const std::string detector = argv[1];
  Cloud::Ptr cloud(new Cloud);
  if (!read_points(argv[2], *cloud)) {
    std::cerr << argv[2] << ": cannot read points\n";
    return 1;
  }
  const auto start = std::chrono::steady_clock::now();
  const double res = resolution(cloud);
  auto tree = pcl::search::KdTree<pcl::PointXYZ>::Ptr(new pcl::search::KdTree<pcl::PointXYZ>);
  Cloud keypoints;
  if (detector == "iss") {
    pcl::ISSKeypoint3D<pcl::PointXYZ, pcl::PointXYZ> iss;
    iss.setSearchMethod(tree);
    iss.setSalientRadius(6 * res);
    iss.setNonMaxRadius(4 * res);
    iss.setThreshold21(0.975);
    iss.setThreshold32(0.975);
    iss.setMinNeighbors(5);
    iss.setInputCloud(cloud);
    iss.compute(keypoints);
  } else if (detector == "harris") {
    pcl::HarrisKeypoint3D<pcl::PointXYZ, pcl::PointXYZI> harris;
    pcl::PointCloud<pcl::PointXYZI> out;
    harris.setSearchMethod(tree);
    harris.setRadius(6 * res);
    harris.setNonMaxSupression(true);
    harris.setRefine(false);  // keep keypoints on input points
    harris.setInputCloud(cloud);
    harris.compute(out);
    for (const auto& p : out.points) keypoints.push_back(pcl::PointXYZ(p.x, p.y, p.z));
  } else {
    std::cerr << "unknown detector '" << detector << "' (iss or harris)\n";
    return 2;
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  pcl::KdTreeFLANN<pcl::PointXYZ> nearest;
  nearest.setInputCloud(cloud);
  std::set<int> indices;
  std::vector<int> index(1);
  std::vector<float> sq(1);
  for (const auto& p : keypoints.points) {
    if (std::isfinite(p.x) && nearest.nearestKSearch(p, 1, index, sq) == 1) indices.insert(index[0]);
  }
  std::ofstream out(argv[3]);
  for (int i : indices) out << i << "\n";
  std::cout << "keypoints " << indices.size() << " seconds " << seconds << "\n";
  return out ? 0 : 1;
}
