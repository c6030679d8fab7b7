#include "core/merge/register.hpp"

#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/registration/icp.h>
#include <pcl/search/kdtree.h>

#include <flann/algorithms/dist.h>
#include <flann/algorithms/kdtree_single_index.h>
#include <flann/util/result_set.h>

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/surface_caster.hpp"

namespace vsm::core {

namespace {

constexpr std::size_t kMinCoarsePoints = 1000;
constexpr std::size_t kMinPoints = 12;

using Grids = std::vector<std::shared_ptr<const PatchGrid>>;

/// The grids of `depth` (or of shallower leaves) whose box meets `box`, found by descending from
/// the root.
Grids gridsAt(PatchSource& source, int depth, const Box3d& box) {
  const Model& model = source.model();
  Grids grids;
  std::vector<PatchKey> pending{PatchKey::root()};
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo& info = model.at(key);
    if (!info.globalBox.intersects(box)) {
      continue;
    }
    if (key.depth >= depth || info.isLeaf()) {
      grids.push_back(source.positions(key));
      continue;
    }
    for (const PatchKey& child : model.children(key)) {
      pending.push_back(child);
    }
  }
  return grids;
}

/// Mean resolution of a model's levels, by depth (0 where unknown).
std::vector<double> levelResolutions(const Model& model) {
  std::vector<double> out(static_cast<std::size_t>(std::max(model.maxDepth() + 1, 1)), 0.0);
  for (const LevelSummary& level : model.levels()) {
    out[static_cast<std::size_t>(level.depth)] = level.resolution;
  }
  return out;
}

/// The depth whose resolution is closest to `resolution` (in ratio).
int closestDepth(const std::vector<double>& resolutions, double resolution) {
  int best = static_cast<int>(resolutions.size()) - 1;
  double bestScore = std::numeric_limits<double>::infinity();
  for (std::size_t d = 0; d < resolutions.size(); ++d) {
    if (resolutions[d] > 0) {
      const double score = std::fabs(std::log(resolutions[d] / resolution));
      if (score < bestScore) {
        bestScore = score;
        best = static_cast<int>(d);
      }
    }
  }
  return best;
}

/// A grid's vertices in global coordinates, each transformed once (a normal needs up to five).
struct GlobalGrid {
  int side = 0;
  std::vector<Vec3d> points;        // row by row; meaningful where defined
  std::vector<std::uint8_t> valid;  // 1 where defined

  /// Takes `g`'s vertices (reusing the buffers: one GlobalGrid serves a model's grids in turn).
  void assign(const PatchGrid& g) {
    side = g.size();
    points.resize(static_cast<std::size_t>(side) * side);
    valid.assign(static_cast<std::size_t>(side) * side, 0);
    for (int y = 0; y < side; ++y) {
      for (int x = 0; x < side; ++x) {
        if (g.defined(x, y)) {
          points[index(x, y)] = g.global(x, y);
          valid[index(x, y)] = 1;
        }
      }
    }
  }
  std::size_t index(int x, int y) const { return static_cast<std::size_t>(y) * side + x; }
  bool defined(int x, int y) const {
    return x >= 0 && y >= 0 && x < side && y < side && valid[index(x, y)] != 0;
  }
  const Vec3d& at(int x, int y) const { return points[index(x, y)]; }
  const Vec3d& global(int x, int y) const { return at(x, y); }
  int size() const { return side; }
};

/// A grid vertex's normal (vec::vertexNormal), oriented along `up`; nullopt when the
/// neighbourhood is too sparse.
std::optional<Vec3d> normalAt(const GlobalGrid& g, int x, int y, const Vec3d& up) {
  const Vec3d n = vec::vertexNormal(g, x, y);
  if (!n.finite()) {
    return std::nullopt;
  }
  return vec::dot(n, up) < 0 ? n * -1.0 : n;
}

struct Cloud {
  std::vector<Vec3d> points;
  std::vector<Vec3d> normals;
};

/// The defined vertices of `grids` that have a normal and pass `keep(position, normal)`, in grid
/// order.
template <typename Keep>
Cloud cloudOf(const Grids& grids, const Vec3d& up, const Keep& keep) {
  Cloud cloud;
  GlobalGrid g;
  for (const auto& grid : grids) {
    g.assign(*grid);
    for (std::size_t i = 0; i < g.points.size(); ++i) {
      if (g.valid[i] == 0) {
        continue;
      }
      const int x = static_cast<int>(i % static_cast<std::size_t>(g.side));
      const int y = static_cast<int>(i / static_cast<std::size_t>(g.side));
      if (const auto n = normalAt(g, x, y, up); n && keep(g.points[i], *n)) {
        cloud.points.push_back(g.points[i]);
        cloud.normals.push_back(*n);
      }
    }
  }
  return cloud;
}

pcl::PointCloud<pcl::PointNormal>::Ptr toPcl(const Cloud& cloud,
                                             const std::vector<std::size_t>& use,
                                             const Vec3d& centre) {
  auto out = pcl::make_shared<pcl::PointCloud<pcl::PointNormal>>();
  out->reserve(use.size());
  for (const std::size_t i : use) {
    pcl::PointNormal p;
    const Vec3d l = cloud.points[i] - centre;
    p.x = static_cast<float>(l.x);
    p.y = static_cast<float>(l.y);
    p.z = static_cast<float>(l.z);
    p.normal_x = static_cast<float>(cloud.normals[i].x);
    p.normal_y = static_cast<float>(cloud.normals[i].y);
    p.normal_z = static_cast<float>(cloud.normals[i].z);
    p.curvature = 0;
    out->push_back(p);
  }
  return out;
}

/// The kd-tree over B's points that ICP and its fitness score search. pcl::search::KdTree asks
/// FLANN through knnSearch(), which opens an OpenMP parallel region for every single query: with
/// libgomp that costs two futex system calls per query even with one thread, about half of each
/// query, and registration makes some 10^5 of them. This is the tree pcl::KdTreeFLANN builds
/// (FLANN's single kd-tree, leaves of at most 15 points, over x, y, z, exact search) queried
/// through findNeighbors() directly: the same neighbours, without the parallel region. It derives
/// from pcl::search::KdTree because that is the type ICP takes; the base's own tree stays empty,
/// and radius search (which ICP does not use) is not offered.
class DirectKdTree final : public pcl::search::KdTree<pcl::PointNormal> {
 public:
  void setInputCloud(const PointCloudConstPtr& cloud,
                     const IndicesConstPtr& indices = IndicesConstPtr()) override {
    input_ = cloud;
    indices_ = indices;
    xyz_.clear();
    ids_.clear();
    index_.reset();
    auto add = [&](pcl::index_t i) {
      const pcl::PointNormal& p = (*cloud)[static_cast<std::size_t>(i)];
      if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) {
        xyz_.insert(xyz_.end(), {p.x, p.y, p.z});
        ids_.push_back(i);
      }
    };
    if (indices) {
      for (const pcl::index_t i : *indices) {
        add(i);
      }
    } else {
      for (std::size_t i = 0; i < cloud->size(); ++i) {
        add(static_cast<pcl::index_t>(i));
      }
    }
    if (!ids_.empty()) {
      index_ = std::make_unique<Index>(flann::Matrix<float>(xyz_.data(), ids_.size(), 3),
                                       flann::KDTreeSingleIndexParams(15));
      index_->buildIndex();
    }
  }

  int nearestKSearch(const pcl::PointNormal& point, int k, pcl::Indices& indices,
                     std::vector<float>& distances) const override {
    const std::size_t n = index_ && k > 0 ? std::min(static_cast<std::size_t>(k), ids_.size()) : 0;
    indices.resize(n);
    distances.resize(n);
    if (n == 0) {
      return 0;
    }
    // The result set knnSearch() uses for k <= 250; squared distances, nearest first.
    flann::KNNSimpleResultSet<float> result(n);
    const float query[3] = {point.x, point.y, point.z};
    index_->findNeighbors(result, query, params_);
    std::size_t one = 0;  // ICP asks for one neighbour: no allocation then
    std::vector<std::size_t> many(n > 1 ? n : 0);
    std::size_t* found = n > 1 ? many.data() : &one;
    result.copy(found, distances.data(), n, true);
    for (std::size_t i = 0; i < n; ++i) {
      indices[i] = ids_[found[i]];
    }
    return static_cast<int>(n);
  }

  int radiusSearch(const pcl::PointNormal&, double, pcl::Indices&, std::vector<float>&,
                   unsigned int) const override {
    throw Error(ErrorCode::Internal, "register: radius search is not offered");
  }

 private:
  using Index = flann::KDTreeSingleIndex<flann::L2_Simple<float>>;
  std::vector<float> xyz_;         // x, y, z per indexed point: FLANN's dataset
  std::vector<pcl::index_t> ids_;  // FLANN's point -> index into the input cloud
  std::unique_ptr<Index> index_;
  flann::SearchParams params_{-1, 0.0f};  // as pcl::KdTreeFLANN: unlimited checks, exact
};

/// 0, 1, ..., count - 1.
std::vector<std::size_t> allIndices(std::size_t count) {
  std::vector<std::size_t> out(count);
  for (std::size_t i = 0; i < count; ++i) {
    out[i] = i;
  }
  return out;
}

/// Every `step`-th index so that at most `limit` remain.
std::vector<std::size_t> thinned(std::vector<std::size_t> indices, std::size_t limit) {
  if (indices.size() <= limit || limit == 0) {
    return indices;
  }
  const double step = static_cast<double>(indices.size()) / static_cast<double>(limit);
  std::vector<std::size_t> out;
  out.reserve(limit);
  for (std::size_t k = 0; k < limit; ++k) {
    out.push_back(indices[static_cast<std::size_t>(static_cast<double>(k) * step)]);
  }
  return out;
}

Mat4d toMat(const Eigen::Matrix4d& e) {
  Mat4d m;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) {
      m.m[static_cast<std::size_t>(r * 4 + c)] = e(r, c);
    }
  }
  return m;
}

/// Milliseconds per step of a stage, for the debug log: where registration spends its time.
class StageClock {
 public:
  explicit StageClock(bool enabled) : enabled_(enabled) {}
  /// Appends " <name> <ms since the previous lap>" when enabled.
  void lap(const char* name) {
    if (!enabled_) {
      return;
    }
    const auto now = std::chrono::steady_clock::now();
    char text[64];
    std::snprintf(text, sizeof text, " %s %.1f", name,
                  std::chrono::duration<double, std::milli>(now - last_).count());
    laps_ += text;
    last_ = now;
  }
  /// The laps so far, then starts over.
  std::string take() { return std::exchange(laps_, std::string()); }

 private:
  bool enabled_;
  std::chrono::steady_clock::time_point last_ = std::chrono::steady_clock::now();
  std::string laps_;
};

Vec3d applyLocal(const Eigen::Matrix4d& u, const Vec3d& centre, const Vec3d& p) {
  const Vec3d l = p - centre;
  const Eigen::Vector4d r = u * Eigen::Vector4d(l.x, l.y, l.z, 1);
  return Vec3d{r.x(), r.y(), r.z()} + centre;
}

/// Direction `d` turned by u's rotation.
Vec3d turnLocal(const Eigen::Matrix4d& u, const Vec3d& d) {
  const Eigen::Vector3d r = u.block<3, 3>(0, 0) * Eigen::Vector3d(d.x, d.y, d.z);
  return {r.x(), r.y(), r.z()};
}

/// Two unit directions perpendicular to unit `n` and to each other.
std::pair<Vec3d, Vec3d> tangents(const Vec3d& n) {
  const Vec3d helper = std::fabs(n.x) < 0.6 ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0};
  Vec3d t1{helper.y * n.z - helper.z * n.y, helper.z * n.x - helper.x * n.z,
           helper.x * n.y - helper.y * n.x};
  t1 = t1 * (1 / t1.norm());
  const Vec3d t2{n.y * t1.z - n.z * t1.y, n.z * t1.x - n.x * t1.z, n.x * t1.y - n.y * t1.x};
  return {t1, t2};
}

}  // namespace

RegistrationResult registerModels(PatchSource& target, PatchSource& detail,
                                  const RegistrationOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  const Model& a = target.model();
  const Model& b = detail.model();
  if (a.empty() || b.empty()) {
    throw Error(ErrorCode::InvalidArgument, "register: the target or the detail model is empty");
  }
  const Box3d bBox = b.at(PatchKey::root()).globalBox;
  if (bBox.empty()) {
    throw Error(ErrorCode::InvalidArgument, "register: the detail model has no defined vertex");
  }
  // `up` only orients the normals (point-to-plane ICP does not need it); everything else is
  // measured on the surfaces, whatever their orientation (issue 33).
  const Vec3d up = options.up ? *options.up : defaultUp(bBox);
  const Vec3d centre = bBox.center();
  // B's extent across its surface: its box's two largest sides (a wall's box is thin along its
  // normal, a terrain's along up).
  std::array<double, 3> sides{bBox.size().x, bBox.size().y, bBox.size().z};
  std::sort(sides.begin(), sides.end());
  const double area = sides[1] * sides[2];

  const std::vector<double> aRes = levelResolutions(a);
  const std::vector<double> bRes = levelResolutions(b);
  // Coarse stage: A's coarsest level with enough vertices over B (estimated from metadata).
  int aCoarse = a.maxDepth();
  for (int d = 0; d <= a.maxDepth(); ++d) {
    const double r = aRes[static_cast<std::size_t>(d)];
    if (r > 0 && area / (r * r) >= static_cast<double>(kMinCoarsePoints)) {
      aCoarse = d;
      break;
    }
  }
  const double aCoarseRes = aRes[static_cast<std::size_t>(aCoarse)];
  const double aFineRes = aRes[static_cast<std::size_t>(a.maxDepth())];
  if (!(aCoarseRes > 0) || !(aFineRes > 0)) {
    throw Error(ErrorCode::InvalidArgument, "register: the target has no measurable resolution");
  }

  struct Stage {
    int aDepth, bDepth;
    double distance;
  };
  std::vector<Stage> stages;
  const double search = options.searchRadius ? *options.searchRadius : 4 * aCoarseRes;
  stages.push_back({aCoarse, closestDepth(bRes, aCoarseRes), search});
  // Refinement: A's bottom vertices against B about twice as fine, shrinking the distance.
  const int bFine = closestDepth(bRes, aFineRes / 2);
  const double bFineRes = bRes[static_cast<std::size_t>(bFine)];
  for (double d = std::min(search / 2, 2 * aFineRes); stages.size() < 6; d /= 2) {
    stages.push_back({a.maxDepth(), bFine, d});
    if (d <= 3 * bFineRes) {
      break;
    }
  }

  RegistrationResult result;
  result.targetDepth = stages.front().aDepth;
  result.detailDepth = stages.front().bDepth;
  Eigen::Matrix4d u = Eigen::Matrix4d::Identity();  // moves A onto B, centred coordinates
  struct DetailLevel {
    Cloud cloud;
    std::shared_ptr<SurfaceCaster> surface;
    pcl::PointCloud<pcl::PointNormal>::Ptr points;
    pcl::search::KdTree<pcl::PointNormal>::Ptr tree;  // built once, shared by the stages
  };
  std::map<int, DetailLevel> bLevels;
  const bool debug = log::level() <= log::Level::Debug;
  StageClock clock(debug);
  for (std::size_t s = 0; s < stages.size(); ++s) {
    if (options.cancel != nullptr) {
      options.cancel->throwIfCancelled();
    }
    if (options.progress != nullptr) {
      options.progress->report("registering", static_cast<double>(s) / stages.size());
    }
    const Stage& stage = stages[s];
    DetailLevel& bLevel = bLevels[stage.bDepth];
    if (!bLevel.surface) {
      const Grids grids = gridsAt(detail, stage.bDepth, bBox);
      bLevel.cloud = cloudOf(grids, up, [](const Vec3d&, const Vec3d&) { return true; });
      bLevel.surface = std::make_shared<SurfaceCaster>(grids);
      bLevel.points =
          toPcl(bLevel.cloud,
                thinned(allIndices(bLevel.cloud.points.size()), options.maxPoints * 4), centre);
      bLevel.tree = pcl::make_shared<DirectKdTree>();
      bLevel.tree->setInputCloud(bLevel.points);
      clock.lap("detail-level");
    }
    const SurfaceCaster& bSurface = *bLevel.surface;

    // A's vertices whose current image lies over B, along its normal within the search distance,
    // with a margin across its surface. The margin keeps B's border from attracting A's vertices
    // that have no partner on B; it never takes more than a quarter of B's width (a B only a few
    // A cells wide must keep some).
    Box3d near = bBox;
    near.min = near.min - Vec3d{stage.distance, stage.distance, stage.distance};
    near.max = near.max + Vec3d{stage.distance, stage.distance, stage.distance};
    const double m = std::min(stage.distance, 0.25 * sides[1]);
    const double reach = stage.distance;
    const Cloud aCloud =
        cloudOf(gridsAt(target, stage.aDepth, near), up, [&](const Vec3d& p, const Vec3d& normal) {
          const Vec3d q = applyLocal(u, centre, p);
          const Vec3d n = turnLocal(u, normal);
          const auto [t1, t2] = tangents(n);
          for (const Vec3d& o : {q, q + t1 * m, q - t1 * m, q + t2 * m, q - t2 * m}) {
            if (!bSurface.cast({o, n, -reach, reach})) {
              return false;
            }
          }
          return true;
        });
    if (aCloud.points.size() < kMinPoints) {
      throw Error(ErrorCode::InvalidArgument,
                  "register: the models overlap too little to register (" +
                      std::to_string(aCloud.points.size()) +
                      " target vertices over the detail model)");
    }
    clock.lap("target-over-detail");
    const std::vector<std::size_t> use =
        thinned(allIndices(aCloud.points.size()), options.maxPoints);
    const auto source = toPcl(aCloud, use, centre);
    clock.lap("thin");
    const auto& targetCloud = bLevel.points;

    pcl::IterativeClosestPointWithNormals<pcl::PointNormal, pcl::PointNormal> icp;
    icp.setInputSource(source);
    icp.setInputTarget(targetCloud);
    icp.setSearchMethodTarget(bLevel.tree, true);
    icp.setMaxCorrespondenceDistance(stage.distance);
    icp.setMaximumIterations(options.maxIterations);
    icp.setTransformationEpsilon(1e-8);
    icp.setEuclideanFitnessEpsilon(1e-10);
    int iterations = 0;  // counted in the debug log only (the callback copies indices)
    using Callback =
        pcl::Registration<pcl::PointNormal, pcl::PointNormal>::UpdateVisualizerCallbackSignature;
    std::function<Callback> countIterations = [&](const auto&, const auto&, const auto&,
                                                  const auto&) { ++iterations; };
    if (debug) {
      icp.registerVisualizationCallback(countIterations);
      iterations = 0;  // registering calls it once
    }
    pcl::PointCloud<pcl::PointNormal> aligned;
    icp.align(aligned, u.cast<float>());
    clock.lap("icp");
    u = icp.getFinalTransformation().cast<double>();
    result.converged = icp.hasConverged();
    result.stages = static_cast<int>(s + 1);
    // The result reports the last stage's quality; earlier stages measure theirs (another nearest
    // neighbour search of every point) only for the debug log.
    if (s + 1 < stages.size() && !debug) {
      continue;
    }
    result.fitness = icp.getFitnessScore(stage.distance);
    clock.lap("fitness");
    // The residual along A's normals: how far A's vertices, moved by u, lie from B's surface.
    double sum = 0;
    std::size_t count = 0;
    for (const std::size_t i : use) {
      const Vec3d q = applyLocal(u, centre, aCloud.points[i]);
      const Vec3d n = turnLocal(u, aCloud.normals[i]);
      if (const auto onB = bSurface.cast({q, n, -reach, reach})) {
        sum += onB->distance * onB->distance;
        ++count;
      }
    }
    result.rms = count > 0 ? std::sqrt(sum / static_cast<double>(count)) : 0;
    clock.lap("rms");
    log::debug("register: stage " + std::to_string(s) + " A depth " + std::to_string(stage.aDepth) +
               " B depth " + std::to_string(stage.bDepth) + " distance " +
               std::to_string(stage.distance) + " points " + std::to_string(source->size()) + "/" +
               std::to_string(targetCloud->size()) + " fitness " + std::to_string(result.fitness) +
               " rms " + std::to_string(result.rms) + " iterations " + std::to_string(iterations) +
               ", ms:" + clock.take());
  }
  if (options.progress != nullptr) {
    options.progress->report("registering", 1);
  }

  // u moves A onto B around `centre`; B needs the inverse, in global coordinates.
  Eigen::Matrix4d shift = Eigen::Matrix4d::Identity();
  shift.block<3, 1>(0, 3) = Eigen::Vector3d(centre.x, centre.y, centre.z);
  Eigen::Matrix4d unshift = Eigen::Matrix4d::Identity();
  unshift.block<3, 1>(0, 3) = -Eigen::Vector3d(centre.x, centre.y, centre.z);
  Eigen::Matrix4d inv = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d r = u.block<3, 3>(0, 0);
  // Re-orthonormalise the float32 rotation so the transform is exactly rigid.
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(r, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d rot = svd.matrixU() * svd.matrixV().transpose();
  if (rot.determinant() < 0) {
    Eigen::Matrix3d fix = Eigen::Matrix3d::Identity();
    fix(2, 2) = -1;
    rot = svd.matrixU() * fix * svd.matrixV().transpose();
  }
  inv.block<3, 3>(0, 0) = rot.transpose();
  inv.block<3, 1>(0, 3) = -rot.transpose() * u.block<3, 1>(0, 3);
  result.transform = toMat(shift * inv * unshift);
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  log::info("register: " + std::to_string(result.stages) + " stages, fitness " +
            std::to_string(result.fitness) + " m2, rms along the target's normals " +
            std::to_string(result.rms) + " m" +
            (result.converged ? ", converged" : ", not converged") + ", " +
            std::to_string(result.seconds) + " s");
  return result;
}

RegistrationResult registerModels(LiveModel& target, LiveModel& detail,
                                  const RegistrationOptions& options) {
  const auto t = liveSource(target);
  const auto d = liveSource(detail);
  return registerModels(*t, *d, options);
}

}  // namespace vsm::core
