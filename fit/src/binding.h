#pragma once
// A fit or sensitivity key resolved once into what it sets: an image's defocus or background,
// the light field's edge, the camera PSF, an object's value or another scene value. The model
// builds the scene once and patches the bound values into a copy per evaluation; keys without
// a typed patch (an index field's scale, a cone's angle, a generated shape's size...) set the
// scene file's value and the scene is read again, as the first build was. Not installed.
#include <optional>
#include <string>
#include <vector>

#include "raymatch/simulate/scene.h"

namespace raymatch::fit::internal {

/// One dot-separated part of a key: a name and an optional [index].
struct KeySegment {
  std::string name;
  std::optional<size_t> index;
};

/// "object.drop.center_um[2]" -> object, drop, center_um[2]; throws Error for a malformed key
/// (fit_file.cpp).
std::vector<KeySegment> SplitKey(const std::string& key);

struct Binding {
  enum class Kind {
    kObject,      ///< object.<name or [i]>.<field>: the object's own value
    kScene,       ///< any other scene value (source, optics, an index field, ...)
    kEdge,        ///< light_field_edge.*: the light field beyond the objective's NA
    kPsf,         ///< camera.psf_sigma_um
    kDefocus,     ///< image[i].defocus_um
    kBackground,  ///< image[i].background_photons / _slope_x / _slope_y
  };
  /// The value a typed patch writes into the built scene; kNone: set in the scene file and read
  /// again.
  enum class Field {
    kNone,
    kCenter,
    kRadius,
    kIndex,
    kRotation,
    kEdgeHalfAngle,
    kEdgeWidth,
    kEdgeTilt,
    kPsfSigma
  };
  Kind kind = Kind::kScene;
  Field field = Field::kNone;
  size_t object = 0;   ///< kObject: position in the scene's object list
  int component = 0;   ///< vector component ([i] of center_um, rotation_deg, tilt_deg)
  size_t image = 0;    ///< kDefocus, kBackground
  int background = 0;  ///< kBackground: 0 level, 1 slope x, 2 slope y

  /// Set in the scene (not an image's own value).
  bool InScene() const { return kind != Kind::kDefocus && kind != Kind::kBackground; }
  /// Its range can move the objects or widen the field the source must cover (every key but the
  /// edge beyond the NA and the PSF): the model probes the parameter box's corners over these.
  bool SpansRegion() const { return kind != Kind::kEdge && kind != Kind::kPsf; }
  /// Rays that miss every object at the start miss them at any value: the objects' own values,
  /// the images', the edge (its own ray population) and the PSF (applied per ray) keep the
  /// near/far split of the traced rays; other scene values (the source, the optics) do not.
  bool KeepsSplit() const { return kind != Kind::kScene; }
  /// Moves its object across the optical axis only (x or y of its centre).
  bool MovesAcross() const {
    return kind == Kind::kObject && field == Field::kCenter && component < 2;
  }
  /// Patched into the built scene without reading the scene file again.
  bool Typed() const { return InScene() && field != Field::kNone; }
};

/// Resolves `key` against the scene `built` (the scene file read once) for a fit with `images`
/// images. Throws Error for a malformed key or an image key that does not exist (scene keys are
/// checked where the fit file is read).
Binding Bind(const std::string& key, const simulate::Scene& built, size_t images);

/// Writes a typed binding's value into `scene` (Binding::Typed()).
void Patch(const Binding& b, double value, simulate::Scene* scene);

}  // namespace raymatch::fit::internal
