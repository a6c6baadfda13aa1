#pragma once
// Physical optics from rays: the angular spectrum of the field that one coherent illumination
// plane wave leaves behind the scene's objects, for any object the tracer handles (spheres,
// meshes, gradient-index fields).
//
// Model (docs/physical-optics.md):
//  * The incident wave E0 exp(i k_in . (r - origin)) is cut at the objects' silhouette: on the
//    z-plane through `origin`, the part whose incident rays meet an object is removed
//    (Kirchhoff's shadow). Its angular spectrum is the silhouette's Fourier transform, a line
//    integral over the silhouette's outline (Green's theorem), the outline found by bisection
//    between rays that meet an object and rays that miss.
//  * What the objects send on is geometrical optics along every branch of the Fresnel splits
//    up to `max_events` surfaces (Simulator::TraceFieldRay: the field, the Fresnel amplitudes
//    with their phases, the optical path). A branch's rays start on a lattice in front of the
//    objects; a lattice cell is halved while the rays' crossings of the exit plane (by
//    default the z-plane through `origin`; the exit rays extended straight, forwards or back)
//    span more than `max_cell_steps` steps of the band's sampling, or where the branch's rays
//    start or stop.
//  * Each lattice triangle is a ray tube: on the exit plane its field is the rays' fields
//    (barycentric) times sqrt(dA_in / (dA_plane cos theta)) exp(i psi - i (pi / 2) N), psi the
//    rays' phases carried to the sampling node along their own wave vectors, N the focal lines
//    the tube passes on its way to the plane (from the triangle its rays make where each
//    straight segment begins and where it ends, on a surface oriented along the surface's
//    normal: mirrored past one, turned about past two; counted negative where the plane lies
//    before the exits). The plane's field is sampled on a periodic grid (`plane_oversample`
//    times finer than the passed band needs), each node taking a triangle's field in the share
//    of its cell that the triangle covers, and Fourier transformed (one DFT per component):
//    A(k_t) = (1 / (2 pi)^2) integral of E(x) exp(-i k_t . x) d^2x, projected transverse to k.
//    With a FieldLayout kept across spectra the lattice and its refinement follow the objects,
//    and the spectrum changes continuously with them.
//  * The scattered field is E_s(r) = integral of A(k_t) exp(i k . (r - origin)) dk_x dk_y, so
//    the field beyond the objects is E0 exp(i k_in . (r - origin)) + E_s; k = 2 pi n_medium /
//    lambda. This is the convention of the Mie model's angular spectrum (wave_image.h), whose
//    exact sphere it is checked against.
//  * Rays steeper than the grid's k_max taper off (a raised cosine over `taper` k_max) and
//    cells wholly beyond the taper are not refined; their power still counts in
//    `branch_power`.
// Limits (measured in docs/physical-optics.md): geometrical optics near the silhouette's rim
// (grazing rays, where the tube amplitude is least right) limits the accuracy at larger
// scattering angles; a branch's rays that fold over (rainbow caustics) give an amplitude that
// diverges at the fold; foci inside gradient-index objects are not counted; features smaller
// than the coarse lattice spacing can be missed.
#include <array>
#include <complex>
#include <cstdint>
#include <map>
#include <vector>

#include "raymatch/simulate/tracer.h"

namespace raymatch::simulate {

using CVec3 = std::array<std::complex<double>, 3>;

/// Nodes (i, j), 0 <= i < nx, 0 <= j < ny, at k_x = kx0 + i dk, k_y = ky0 + j dk (rad / um in the
/// medium); nodes with |k_t| > k_max are left at 0 (an objective passes k NA / n_medium).
struct SpectrumGrid {
  int nx = 0, ny = 0;
  double kx0 = 0, ky0 = 0, dk = 0, k_max = 0;
};

struct RaySpectrumSettings {
  double ray_spacing_um = 0;  ///< the coarse lattice (0: the medium's wavelength)
  int refine_levels = 6;      ///< halvings of a lattice cell at most
  double max_cell_steps = 1;  ///< a cell is halved while its exit-plane image spans more band steps
  int max_events = 4;         ///< surface events of the longest branch (0: the shadow alone)
  double taper = 0.15;        ///< width of the taper beyond k_max, as a fraction of k_max
  /// The exit plane's sampling step is the passed band's (pi / (1.25 k_end), k_end where the
  /// taper ends) over this; the lattice refines to the band's step.
  double plane_oversample = 4;
  /// The branches' exit plane, along z from `origin` (um); the shadow is cut on the plane
  /// through `origin`. The geometrical field is cut at its edge where it is sampled, and
  /// that edge diffracts from there: the plane through a sphere's centre (0) is the one that
  /// agrees with Mie theory (docs/physical-optics.md); the grid's window (2 pi / dk) must hold
  /// the branches' light on the plane.
  double exit_plane_um = 0;
};

struct RaySpectrum {
  std::vector<CVec3> a;    ///< [j * nx + i]: the scattered field's spectrum density
  int branches = 0;        ///< branches (reflect / refract sequences) with rays
  uint64_t rays = 0;       ///< field rays traced
  uint64_t triangles = 0;  ///< lattice triangles mapped
  /// The power the branches send forward (sum of |E_out|^2 dA_in over their lattice cells,
  /// before the taper); what a non-absorbing object does not send forward it reflects back or
  /// keeps past `max_events`.
  double branch_power = 0;
  /// The same power as the exit plane's samples carry it (the sum over the plane's nodes of
  /// |E|^2 cos theta times the node's area, each ray tube's own, without the interference where
  /// tubes overlap, after the taper): the tubes' amplitudes conserve what the lattice sent.
  double plane_power = 0;
  double shadow_area_um2 = 0;  ///< the silhouette's area on the origin's z-plane
  int outline_segments = 0;    ///< of the silhouette's outline
};

/// The field rays' layout for one illumination wave, kept from one spectrum to the next (a
/// fit's evaluations): the lattice's cell counts, its corner and spacing relative to the
/// objects' shadow box on the start plane, and each branch's halved edges. A spectrum made with
/// an empty layout records it; later ones replay it, the lattice scaled and moved with the box
/// and every refinement decision as recorded, so the sampling follows the objects continuously
/// instead of jumping where a cell count or a refinement test flips (a sphere's lattice then
/// scales with its radius: which rays hit it does not change). Where the box no longer fits in
/// the scaled lattice, the layout is recorded again.
struct FieldLayout {
  bool recorded = false;
  int64_t ni = 0, nj = 0;        ///< coarse cells along x and y
  double spacing = 0;            ///< the coarse spacing at recording (um)
  double x_lo = 0, y_lo = 0;     ///< the lattice's corner at recording
  double box[4] = {0, 0, 0, 0};  ///< the shadow box then: x_lo, y_lo, x_hi, y_hi
  std::map<uint64_t, std::vector<uint64_t>> halved;  ///< branch -> halved edges (sorted keys)
};

/// The angular spectrum (above) of the plane wave of direction `direction` (unit, d.z > 0)
/// and field `e0` (perpendicular to it, its value at `origin`) behind `sim`'s objects, on
/// `grid`. The same result for any thread count.
RaySpectrum RayAngularSpectrum(const Simulator& sim, const Vec3& direction, const CVec3& e0,
                               const Vec3& origin, const SpectrumGrid& grid,
                               const RaySpectrumSettings& settings = {});

/// The same for several fields of one direction (e.g. two polarisations), one spectrum each:
/// the silhouette's outline and transform are found once for all of them.
/// With `layout`, the field rays are laid out as it says (recording it when it is empty).
std::vector<RaySpectrum> RayAngularSpectra(const Simulator& sim, const Vec3& direction,
                                           const std::vector<CVec3>& e0s, const Vec3& origin,
                                           const SpectrumGrid& grid,
                                           const RaySpectrumSettings& settings = {},
                                           FieldLayout* layout = nullptr);

}  // namespace raymatch::simulate
