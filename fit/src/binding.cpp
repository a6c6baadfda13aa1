#include "binding.h"

#include "raymatch/core/error.h"
#include "raymatch/fit/fit.h"

namespace raymatch::fit::internal {

namespace {

/// The object an object key names (object[i] or object.<name>) and the rest of the key.
std::optional<std::pair<size_t, std::vector<KeySegment>>> ObjectOf(
    const std::vector<KeySegment>& parts, const simulate::Scene& built) {
  if (parts.size() < 2) return std::nullopt;
  if (parts[0].index) {
    if (*parts[0].index >= built.objects.size()) return std::nullopt;
    return std::pair(*parts[0].index, std::vector<KeySegment>(parts.begin() + 1, parts.end()));
  }
  // By name: the one object of that name (two of one name are left to the scene file's
  // reading, which takes the last).
  std::optional<size_t> found;
  for (size_t k = 0; k < built.objects.size(); ++k)
    if (built.objects[k].name == parts[1].name) {
      if (found) return std::nullopt;
      found = k;
    }
  if (!found || parts.size() < 3 || parts[1].index) return std::nullopt;
  return std::pair(*found, std::vector<KeySegment>(parts.begin() + 2, parts.end()));
}

}  // namespace

Binding Bind(const std::string& key, const simulate::Scene& built, size_t images) {
  Binding b;
  using K = Binding::Kind;
  using F = Binding::Field;
  const std::vector<KeySegment> parts = SplitKey(key);
  if (parts[0].name == "image") {
    const auto image_key = ParseImageKey(key, images);
    if (!image_key) throw Error("key '" + key + "': " + ImageKeysHelp(images));
    b.image = image_key->first;
    const std::string& f = image_key->second;
    b.kind = f == "defocus_um" ? K::kDefocus : K::kBackground;
    b.background = f == "background_slope_x" ? 1 : f == "background_slope_y" ? 2 : 0;
    return b;
  }
  if (parts[0].name == "light_field_edge" && parts.size() == 2) {
    b.kind = K::kEdge;
    const KeySegment& p = parts[1];
    if (p.name == "half_angle_deg" && !p.index) b.field = F::kEdgeHalfAngle;
    if (p.name == "width_deg" && !p.index) b.field = F::kEdgeWidth;
    if (p.name == "tilt_deg" && p.index && *p.index < 2)
      b.field = F::kEdgeTilt, b.component = int(*p.index);
    return b;
  }
  if (key == "camera.psf_sigma_um") {
    b.kind = K::kPsf;
    b.field = F::kPsfSigma;
    return b;
  }
  if (parts[0].name != "object") return b;  // another scene value
  b.kind = K::kObject;
  const auto object = ObjectOf(parts, built);
  if (!object || object->second.size() != 1) return b;
  b.object = object->first;
  const KeySegment& p = object->second[0];
  const simulate::ObjectSpec& o = built.objects[b.object];
  using simulate::ShapeType;
  if (p.name == "center_um" && p.index && *p.index < 3) {
    b.field = F::kCenter, b.component = int(*p.index);
  } else if (p.name == "radius_um" && !p.index && o.shape == ShapeType::kSphere && !o.index_field) {
    // An index field inside a sphere takes the sphere's radius when read: read again.
    b.field = F::kRadius;
  } else if (p.name == "index" && !p.index && !o.index_field &&
             o.dispersion.law == simulate::DispersionLaw::kNone) {
    b.field = F::kIndex;
  } else if (p.name == "rotation_deg" && p.index && *p.index < 3 && !o.index_field &&
             (o.shape == ShapeType::kEllipsoid || o.shape == ShapeType::kBox ||
              (o.shape == ShapeType::kMesh && !o.mesh))) {
    // A mesh from a file turns when the tracer builds it; a generated shape (revolution,
    // iso-surface) and an index field are read again.
    b.field = F::kRotation, b.component = int(*p.index);
  }
  return b;
}

void Patch(const Binding& b, double v, simulate::Scene* s) {
  using F = Binding::Field;
  auto component = [&](Vec3& x) { (b.component == 0 ? x.x : b.component == 1 ? x.y : x.z) = v; };
  switch (b.field) {
    case F::kCenter:
      component(s->objects.at(b.object).center_um);
      break;
    case F::kRadius:
      s->objects.at(b.object).radius_um = v;
      break;
    case F::kIndex:
      s->objects.at(b.object).index = v;
      break;
    case F::kRotation:
      component(s->objects.at(b.object).rotation_deg);
      break;
    case F::kEdgeHalfAngle:
      s->source.edge_half_angle_deg = v;
      break;
    case F::kEdgeWidth:
      s->source.edge_width_deg = v;
      break;
    case F::kEdgeTilt:
      s->source.edge_tilt_deg[size_t(b.component)] = v;
      break;
    case F::kPsfSigma:
      s->camera.psf_sigma_um = v;
      break;
    case F::kNone:
      break;
  }
}

}  // namespace raymatch::fit::internal
