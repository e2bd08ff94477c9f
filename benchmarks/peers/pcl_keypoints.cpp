// PCL keypoint peer for benchmarks/saliency.py and perception.saliency ("pcl_harris", "pcl_iss"):
// ISS 3D and Harris 3D on a point file.
//
// usage: pcl_keypoints iss|harris INPUT.xyz|INPUT.ply OUTPUT.txt [RESPONSES.txt]
// Reads points (a text file of "x y z" or "x y z nx ny nz" lines, or a PLY), detects keypoints, writes the
// indices of the input points nearest to them (one per line, sorted, unique) to OUTPUT, and prints the
// detection time in seconds (file I/O excluded) as the last word on stdout. With RESPONSES, also writes each
// keypoint's detector response there, one per line in the order of OUTPUT: the Harris 3D response for
// harris, the smallest eigenvalue of the scatter matrix within the salient radius (ISS's saliency) for iss.
// Radii follow Open3D's ISS defaults so the two are comparable: resolution = mean nearest-neighbour
// distance; ISS salient radius 6 x resolution, non-maximum radius 4 x, thresholds 0.975, min 5 neighbours.
// Harris 3D uses the salient radius with non-maximum suppression, and the given normals when the input has
// them (else PCL estimates them within that radius). Single-threaded, so runs are repeatable.

#include <pcl/io/ply_io.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/keypoints/harris_3d.h>
#include <pcl/keypoints/iss_3d.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>

#include <Eigen/Eigenvalues>

#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

using Cloud = pcl::PointCloud<pcl::PointXYZ>;
using Normals = pcl::PointCloud<pcl::Normal>;

// Points, and normals when every line has six numbers. False: unreadable, empty, or mixed line lengths.
static bool read_points(const std::string& path, Cloud& cloud, Normals& normals) {
  if (path.size() > 4 && path.substr(path.size() - 4) == ".ply") {
    return pcl::io::loadPLYFile(path, cloud) == 0;
  }
  std::ifstream in(path);
  if (!in) return false;
  std::string line;
  std::size_t columns = 0;
  while (std::getline(in, line)) {
    std::istringstream row(line);
    std::vector<float> v;
    float x;
    while (row >> x) v.push_back(x);
    if (v.empty()) continue;
    if (v.size() != 3 && v.size() != 6) return false;
    if (columns == 0) columns = v.size();
    if (v.size() != columns) return false;
    cloud.push_back(pcl::PointXYZ(v[0], v[1], v[2]));
    if (columns == 6) normals.push_back(pcl::Normal(v[3], v[4], v[5]));
  }
  return !cloud.empty();
}

// ISS's saliency of one point: the smallest eigenvalue of sum (q - p)(q - p)^T over the neighbours q within
// the radius (as pcl::ISSKeypoint3D computes it before non-maximum suppression).
static double iss_response(const Cloud& cloud, pcl::search::KdTree<pcl::PointXYZ>& tree, int index, double radius) {
  std::vector<int> near;
  std::vector<float> sq;
  tree.radiusSearch(cloud[index], radius, near, sq);
  const Eigen::Vector3d p = cloud[index].getVector3fMap().cast<double>();
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int k : near) {
    const Eigen::Vector3d d = cloud[k].getVector3fMap().cast<double>() - p;
    scatter += d * d.transpose();
  }
  return Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter, Eigen::EigenvaluesOnly).eigenvalues()(0);
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
  if (argc != 4 && argc != 5) {
    std::cerr << "usage: " << argv[0] << " iss|harris INPUT.xyz|INPUT.ply OUTPUT.txt [RESPONSES.txt]\n";
    return 2;
  }
  const std::string detector = argv[1];
  Cloud::Ptr cloud(new Cloud);
  Normals::Ptr normals(new Normals);
  if (!read_points(argv[2], *cloud, *normals)) {
    std::cerr << argv[2] << ": cannot read points\n";
    return 1;
  }
  const auto start = std::chrono::steady_clock::now();
  const double res = resolution(cloud);
  auto tree = pcl::search::KdTree<pcl::PointXYZ>::Ptr(new pcl::search::KdTree<pcl::PointXYZ>);
  Cloud keypoints;
  std::vector<float> responses;  // per keypoint (Harris only; ISS's are computed after)
  if (detector == "iss") {
    pcl::ISSKeypoint3D<pcl::PointXYZ, pcl::PointXYZ> iss;
    iss.setSearchMethod(tree);
    iss.setSalientRadius(6 * res);
    iss.setNonMaxRadius(4 * res);
    iss.setThreshold21(0.975);
    iss.setThreshold32(0.975);
    iss.setMinNeighbors(5);
    iss.setNumberOfThreads(1);
    iss.setInputCloud(cloud);
    iss.compute(keypoints);
  } else if (detector == "harris") {
    pcl::HarrisKeypoint3D<pcl::PointXYZ, pcl::PointXYZI> harris;
    pcl::PointCloud<pcl::PointXYZI> out;
    harris.setSearchMethod(tree);
    harris.setRadius(6 * res);
    harris.setNonMaxSupression(true);
    harris.setRefine(false);  // keep keypoints on input points
    harris.setNumberOfThreads(1);
    if (!normals->empty()) harris.setNormals(normals);
    harris.setInputCloud(cloud);
    harris.compute(out);
    for (const auto& p : out.points) {
      keypoints.push_back(pcl::PointXYZ(p.x, p.y, p.z));
      responses.push_back(p.intensity);
    }
  } else {
    std::cerr << "unknown detector '" << detector << "' (iss or harris)\n";
    return 2;
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  pcl::KdTreeFLANN<pcl::PointXYZ> nearest;
  nearest.setInputCloud(cloud);
  std::map<int, double> indices;  // input index -> response (the largest, if two keypoints share a point)
  std::vector<int> index(1);
  std::vector<float> sq(1);
  for (std::size_t k = 0; k < keypoints.size(); ++k) {
    const auto& p = keypoints[k];
    if (!std::isfinite(p.x) || nearest.nearestKSearch(p, 1, index, sq) != 1) continue;
    const double r = k < responses.size() ? responses[k] : -HUGE_VAL;
    auto found = indices.find(index[0]);
    if (found == indices.end() || r > found->second) indices[index[0]] = r;
  }
  std::ofstream out(argv[3]);
  for (const auto& [i, r] : indices) out << i << "\n";
  if (argc == 5) {
    pcl::search::KdTree<pcl::PointXYZ> search;
    search.setInputCloud(cloud);
    std::ofstream rout(argv[4]);
    rout.precision(9);
    for (const auto& [i, r] : indices) rout << (detector == "iss" ? iss_response(*cloud, search, i, 6 * res) : r) << "\n";
    if (!rout) return 1;
  }
  std::cout << "keypoints " << indices.size() << " seconds " << seconds << "\n";
  return out ? 0 : 1;
}
