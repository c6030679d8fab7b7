#include "core/grid/geometry.hpp"

#include <algorithm>
#include <array>

namespace vsm::core {

void Box3d::extend(const Box3d& b) {
  if (!b.empty()) {
    extend(b.min);
    extend(b.max);
  }
}

bool Box3d::contains(const Box3d& b, double tolerance) const {
  if (b.empty()) {
    return true;
  }
  return b.min.x >= min.x - tolerance && b.min.y >= min.y - tolerance &&
         b.min.z >= min.z - tolerance && b.max.x <= max.x + tolerance &&
         b.max.y <= max.y + tolerance && b.max.z <= max.z + tolerance;
}

bool Box3d::intersects(const Box3d& b) const {
  if (empty() || b.empty()) {
    return false;
  }
  return min.x <= b.max.x && b.min.x <= max.x && min.y <= b.max.y && b.min.y <= max.y &&
         min.z <= b.max.z && b.min.z <= max.z;
}

Mat4d Mat4d::translation(const Vec3d& t) {
  Mat4d r;
  r.m[3] = t.x;
  r.m[7] = t.y;
  r.m[11] = t.z;
  return r;
}

bool Mat4d::isTranslation() const {
  return m[0] == 1 && m[1] == 0 && m[2] == 0 && m[4] == 0 && m[5] == 1 && m[6] == 0 && m[8] == 0 &&
         m[9] == 0 && m[10] == 1 && m[12] == 0 && m[13] == 0 && m[14] == 0 && m[15] == 1;
}

namespace {
double det3(const std::array<double, 16>& a) {
  return a[0] * (a[5] * a[10] - a[6] * a[9]) - a[1] * (a[4] * a[10] - a[6] * a[8]) +
         a[2] * (a[4] * a[9] - a[5] * a[8]);
}
}  // namespace

bool Mat4d::isAffineInvertible() const {
  if (m[12] != 0 || m[13] != 0 || m[14] != 0 || m[15] != 1) {
    return false;
  }
  const double d = det3(m);
  return std::isfinite(d) && d != 0;
}

Mat4d Mat4d::inverse() const {
  const double d = det3(m);
  Mat4d r;
  // Inverse of the 3x3 linear part by cofactors.
  r.m[0] = (m[5] * m[10] - m[6] * m[9]) / d;
  r.m[1] = (m[2] * m[9] - m[1] * m[10]) / d;
  r.m[2] = (m[1] * m[6] - m[2] * m[5]) / d;
  r.m[4] = (m[6] * m[8] - m[4] * m[10]) / d;
  r.m[5] = (m[0] * m[10] - m[2] * m[8]) / d;
  r.m[6] = (m[2] * m[4] - m[0] * m[6]) / d;
  r.m[8] = (m[4] * m[9] - m[5] * m[8]) / d;
  r.m[9] = (m[1] * m[8] - m[0] * m[9]) / d;
  r.m[10] = (m[0] * m[5] - m[1] * m[4]) / d;
  const Vec3d t = translationPart();
  r.m[3] = -(r.m[0] * t.x + r.m[1] * t.y + r.m[2] * t.z);
  r.m[7] = -(r.m[4] * t.x + r.m[5] * t.y + r.m[6] * t.z);
  r.m[11] = -(r.m[8] * t.x + r.m[9] * t.y + r.m[10] * t.z);
  return r;
}

Box3d transformBox(const Mat4d& m, const Box3d& box) {
  Box3d result;
  if (box.empty()) {
    return result;
  }
  for (int corner = 0; corner < 8; ++corner) {
    result.extend(m.apply({(corner & 1) != 0 ? box.max.x : box.min.x,
                           (corner & 2) != 0 ? box.max.y : box.min.y,
                           (corner & 4) != 0 ? box.max.z : box.min.z}));
  }
  return result;
}

Vec3d upAt(const Vec3d& p) {
  const double norm = p.norm();
  if (norm > kBodyCentredRadius) {
    return p * (1.0 / norm);
  }
  return {0, 0, 1};
}

Vec3d defaultUp(const Box3d& box) {
  return box.empty() ? Vec3d{0, 0, 1} : upAt(box.center());
}

}  // namespace vsm::core
