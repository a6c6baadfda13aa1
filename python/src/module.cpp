// The raymatch Python module (_raymatch, wrapped by python/raymatch/__init__.py): exceptions,
// scenes and simulation. It calls the libraries as apps/simulate.cpp does, so an image is
// bit-identical to the CLI's for the same scene and seed.
#include <filesystem>

#include "common.h"
#include "raymatch/compare/measures.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/core/version.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/scan.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/wave_image.h"

namespace fs = std::filesystem;

namespace raymatch::python {

namespace {

/// A scene and whether it was read from a file (then sidecars carry the file's checksum).
struct PyScene {
  simulate::Scene scene;
  bool from_file = false;
};

const char* KindName(compare::FailureKind k) {
  switch (k) {
    case compare::FailureKind::kSizeMismatch:
      return "size_mismatch";
    case compare::FailureKind::kFileError:
      return "file_error";
    default:
      return "invalid_input";
  }
}

// ---------------------------------------------------------------------------------------------
// Python dict -> TOML table, so a scene can be built in code and read by the same strict
// reader as a file (unknown keys, wrong types and impossible values are errors alike).

void Insert(toml::table& t, const std::string& key, const py::handle& v, const std::string& path);

std::string Where(const std::string& path) { return path.empty() ? "the scene" : "'" + path + "'"; }

// Where a converted value goes: two fixed adder types keep the recursion to two instantiations.
struct TableAdder {
  toml::table& t;
  const std::string& key;
  template <class N>
  void operator()(N&& node) const {
    t.insert_or_assign(key, std::forward<N>(node));
  }
};
struct ArrayAdder {
  toml::array& a;
  template <class N>
  void operator()(N&& node) const {
    a.push_back(std::forward<N>(node));
  }
};

template <class Add>
void AddValue(const py::handle& v, const std::string& path, const Add& add) {
  if (py::isinstance<py::bool_>(v)) {
    add(toml::value<bool>(v.cast<bool>()));
  } else if (py::isinstance<py::str>(v)) {
    add(toml::value<std::string>(v.cast<std::string>()));
  } else if (py::isinstance<py::dict>(v)) {
    toml::table sub;
    for (auto item : v.cast<py::dict>()) {
      if (!py::isinstance<py::str>(item.first))
        throw py::type_error("scene dict: keys must be strings, got " +
                             std::string(py::str(py::repr(item.first))) + " in " + Where(path));
      const std::string k = item.first.cast<std::string>();
      Insert(sub, k, item.second, path.empty() ? k : path + "." + k);
    }
    add(std::move(sub));
  } else if (py::hasattr(v, "tolist")) {  // NumPy arrays and scalars
    AddValue(v.attr("tolist")(), path, add);
  } else if (py::isinstance<py::int_>(v)) {
    add(toml::value<int64_t>(v.cast<int64_t>()));
  } else if (py::isinstance<py::float_>(v)) {
    add(toml::value<double>(v.cast<double>()));
  } else if (py::isinstance<py::sequence>(v)) {
    toml::array arr;
    size_t i = 0;
    for (py::handle e : v.cast<py::sequence>())
      AddValue(e, path + "[" + std::to_string(i++) + "]", ArrayAdder{arr});
    add(std::move(arr));
  } else {
    throw py::type_error("scene dict: " + Where(path) + " holds a " +
                         std::string(py::str(v.get_type().attr("__name__"))) +
                         "; expected bool, int, float, str, list or dict");
  }
}

void Insert(toml::table& t, const std::string& key, const py::handle& v, const std::string& path) {
  if (v.is_none()) return;  // None = key absent (the reader's default applies)
  AddValue(v, path, TableAdder{t, key});
}

toml::table DictToToml(const py::dict& d) {
  toml::table t;
  for (auto item : d) {
    if (!py::isinstance<py::str>(item.first))
      throw py::type_error("scene dict: keys must be strings, got " +
                           std::string(py::str(py::repr(item.first))));
    const std::string k = item.first.cast<std::string>();
    Insert(t, k, item.second, k);
  }
  return t;
}

/// The name that stands for a scene not read from a file: "<string>" or "<dict>", placed in
/// base_dir (when given) so that relative file names in the scene resolve against it.
std::string SourceName(const std::string& label, const std::optional<std::string>& base_dir) {
  return base_dir ? (fs::path(*base_dir) / label).string() : label;
}

PyScene SceneFromTable(toml::table t, const std::string& source) {
  if (!t.contains("name")) t.insert("name", "scene");  // the default would be the file stem
  return PyScene{simulate::LoadScene(t, source), false};
}

// ---------------------------------------------------------------------------------------------
// simulate: apps/simulate.cpp's RunSimulate and simulate::RunScan without the files.

py::tuple Simulate(const PyScene& ps, std::optional<uint64_t> rays,
                   std::optional<std::vector<double>> defocus_um, std::optional<int64_t> seed,
                   std::optional<double> photons_per_pixel, int threads, bool progress) {
  simulate::Scene scene = ps.scene;
  if (seed) {
    if (*seed < 0) throw py::value_error("seed must be >= 0, got " + std::to_string(*seed));
    scene.trace.seed = static_cast<uint64_t>(*seed);
  }
  if (defocus_um) {
    if (defocus_um->empty())
      throw py::value_error("defocus_um is empty: give at least one focal-plane position (um)");
    scene.defocus_um = *defocus_um;
  }
  if (photons_per_pixel && *photons_per_pixel > 0) {
    scene.trace.photons_per_pixel = *photons_per_pixel;
    scene.trace.rays = 0;
  }
  if (threads > 0) scene.trace.threads = threads;
  if (rays && *rays == 0) throw py::value_error("rays must be > 0 (omit it to use the scene's)");
  simulate::ValidateScene(scene);  // messages name the file, '<string>' or '<dict>'
  simulate::CheckPlanePositions(scene);
  const std::string source = scene.file;
  // The sidecar records the scene file's checksum; a scene from a string or dict has no file.
  if (!ps.from_file) scene.file.clear();

  std::unique_ptr<simulate::Simulator> sim;
  std::unique_ptr<simulate::MieImager> mie;        // optics = "mie": the exact wave image
  std::unique_ptr<simulate::PhysicalImager> phys;  // optics = "physical"
  uint64_t rays_per_image = 0;
  double hits_per_ray = 0;
  {
    py::gil_scoped_release nogil;
    if (scene.trace.optics == simulate::ImageOptics::kMie)
      mie = std::make_unique<simulate::MieImager>(scene);
    else if (scene.trace.optics == simulate::ImageOptics::kPhysical)
      phys = std::make_unique<simulate::PhysicalImager>(scene);
    else
      sim = std::make_unique<simulate::Simulator>(scene);
    if (mie || phys)
      rays_per_image = 0;
    else if (rays)
      rays_per_image = *rays;
    else if (scene.trace.rays > 0)
      rays_per_image = scene.trace.rays;
    else
      rays_per_image = sim->RaysForPhotonTarget(scene.trace.photons_per_pixel, &hits_per_ray);
  }
  py::list images, sidecars, code_values;
  for (size_t i = 0; i < scene.defocus_um.size(); ++i) {
    const double dz = scene.defocus_um[i];
    simulate::RunControl ctl;
    ctl.progress = progress;
    char label[64];
    std::snprintf(label, sizeof label, "plane %zu/%zu z=%+.2f um", i + 1, scene.defocus_um.size(),
                  dz);
    ctl.label = label;
    simulate::PlaneResult r;
    nlohmann::json meta;
    {
      py::gil_scoped_release nogil;
      if (mie) {
        r = simulate::MiePlane(*mie, dz, static_cast<uint32_t>(i), ctl, &meta);
      } else if (phys) {
        r = simulate::PhysicalPlane(*phys, dz, static_cast<uint32_t>(i), ctl, &meta);
      } else {
        r = sim->TracePlane(dz, static_cast<uint32_t>(i), rays_per_image, ctl);
        meta = simulate::PlaneMetadata(*sim, r, static_cast<uint32_t>(i));
      }
    }
    if (!ps.from_file) meta["scene_file"] = source;
    Image dn;
    nlohmann::json readout;
    if (simulate::CodeValues(scene, r.counts, static_cast<uint32_t>(i), &dn, &readout)) {
      meta["code_values"] = readout;
      code_values.append(ToArray(std::move(dn)));
    }
    images.append(ToArray(std::move(r.counts)));
    sidecars.append(ToPython(meta));
    if (PyErr_CheckSignals() != 0) throw py::error_already_set();  // Ctrl-C between planes
  }
  return py::make_tuple(images, py::cast(scene.defocus_um), sidecars, rays_per_image, hits_per_ray,
                        py::cast(mie    ? mie->Effects()
                                 : phys ? phys->Effects()
                                        : sim->Effects()),
                        code_values);
}

}  // namespace

void BindScene(py::module_& m) {
  py::class_<PyScene>(
      m, "Scene",
      "A scene (docs/scene-format.md), read and checked by the same strict reader as "
      "`raymatch simulate`. Build one with Scene.from_file, Scene.from_toml or "
      "Scene.from_dict. Lengths in micrometres.")
      .def_static(
          "from_file",
          [](const py::object& path) {
            const std::string p = PathArg(path);
            return PyScene{simulate::LoadScene(p), true};
          },
          py::arg("path"),
          "Reads a scene file (.toml). Raises raymatch.Error 'file:line:col: error: ...'.")
      .def_static(
          "from_toml",
          [](const std::string& text, std::optional<py::object> base_dir) {
            std::optional<std::string> base;
            if (base_dir && !base_dir->is_none()) base = PathArg(*base_dir);
            const std::string source = SourceName("<string>", base);
            return SceneFromTable(ParseTomlString(text, source), source);
          },
          py::arg("text"), py::arg("base_dir") = py::none(),
          "A scene from TOML text. Relative file names in it resolve against base_dir (default: "
          "the working directory); errors name '<string>:line:col'. name defaults to 'scene'.")
      .def_static(
          "from_dict",
          [](const py::dict& d, std::optional<py::object> base_dir) {
            std::optional<std::string> base;
            if (base_dir && !base_dir->is_none()) base = PathArg(*base_dir);
            const std::string source = SourceName("<dict>", base);
            return SceneFromTable(DictToToml(d), source);
          },
          py::arg("scene"), py::arg("base_dir") = py::none(),
          "A scene from a dict shaped like the TOML file (tables = dicts, [[object]] = list of "
          "dicts, e.g. {'camera': {'pixels': [64, 48], 'pixel_pitch_um': 20}, 'object': [{...}]}). "
          "None values are left out; NumPy arrays and scalars are accepted. name defaults to "
          "'scene'.")
      .def_property_readonly("name", [](const PyScene& s) { return s.scene.name; })
      .def_property_readonly(
          "file", [](const PyScene& s) { return s.scene.file; },
          "The scene file, or '<string>' / '<dict>' (in base_dir if given)")
      .def_property(
          "defocus_um", [](const PyScene& s) { return s.scene.defocus_um; },
          [](PyScene& s, const std::vector<double>& v) {
            if (v.empty()) throw py::value_error("defocus_um needs at least one position (um)");
            s.scene.defocus_um = v;
          },
          "Focal-plane positions in um (+ = towards the camera), the scene's [scan]")
      .def_property(
          "seed", [](const PyScene& s) { return s.scene.trace.seed; },
          [](PyScene& s, uint64_t v) { s.scene.trace.seed = v; })
      .def_property(
          "rays", [](const PyScene& s) { return s.scene.trace.rays; },
          [](PyScene& s, uint64_t v) { s.scene.trace.rays = v; },
          "Rays per image (0: derived from photons_per_pixel)")
      .def_property(
          "photons_per_pixel", [](const PyScene& s) { return s.scene.trace.photons_per_pixel; },
          [](PyScene& s, double v) { s.scene.trace.photons_per_pixel = v; },
          "Target mean hits per flat-field pixel (used when rays is 0)")
      .def_property(
          "threads", [](const PyScene& s) { return s.scene.trace.threads; },
          [](PyScene& s, int v) { s.scene.trace.threads = v; }, "Worker threads (0 = all cores)")
      .def_property_readonly(
          "pixels",
          [](const PyScene& s) { return py::make_tuple(s.scene.camera.nx, s.scene.camera.ny); },
          "(columns, rows) of the camera")
      .def_property_readonly("pixel_pitch_um",
                             [](const PyScene& s) { return s.scene.camera.pixel_pitch_um; })
      .def_property_readonly("wavelength_um",
                             [](const PyScene& s) { return s.scene.wavelength_um; })
      .def_property_readonly("object_names",
                             [](const PyScene& s) {
                               std::vector<std::string> n;
                               for (const auto& o : s.scene.objects) n.push_back(o.name);
                               return n;
                             })
      .def_property_readonly(
          "warnings", [](const PyScene& s) { return s.scene.warnings; },
          "Non-fatal notes from loading (the CLI prints them)")
      .def("__repr__", [](const PyScene& s) {
        return "<raymatch.Scene '" + s.scene.name + "' from " + s.scene.file + ": " +
               std::to_string(s.scene.camera.nx) + "x" + std::to_string(s.scene.camera.ny) +
               " px, " + std::to_string(s.scene.objects.size()) + " object(s), " +
               std::to_string(s.scene.defocus_um.size()) + " plane(s)>";
      });

  m.def("_simulate", &Simulate, py::arg("scene"), py::arg("rays") = py::none(),
        py::arg("defocus_um") = py::none(), py::arg("seed") = py::none(),
        py::arg("photons_per_pixel") = py::none(), py::arg("threads") = 0,
        py::arg("progress") = false);
}

}  // namespace raymatch::python

PYBIND11_MODULE(_raymatch, m) {
  namespace rp = raymatch::python;
  namespace py = pybind11;
  m.doc() = "raymatch: ray-traced brightfield microscope images of transparent objects (C++ core)";
  m.attr("__version__") = raymatch::kVersion;

  // raymatch.Error carries the message the CLI prints after "raymatch: ", and its parts.
  // Leaked on purpose: the types must outlive every module object (pybind11 2.10 idiom).
  static auto* error_type = new py::exception<raymatch::Error>(m, "Error", PyExc_RuntimeError);
  static auto* compare_error_type =
      new py::exception<raymatch::compare::CompareError>(m, "CompareError", error_type->ptr());
  py::register_exception_translator([](std::exception_ptr p) {
    auto raise = [](py::object type, const raymatch::Error& e, const char* kind) {
      py::object inst = type(e.what());
      inst.attr("message") = e.message();
      inst.attr("file") = e.where().file;
      inst.attr("line") = e.where().line;
      inst.attr("column") = e.where().column;
      if (kind) inst.attr("kind") = kind;
      PyErr_SetObject(type.ptr(), inst.ptr());
    };
    try {
      if (p) std::rethrow_exception(p);
    } catch (const raymatch::compare::CompareError& e) {
      raise(*compare_error_type, e, rp::KindName(e.kind()));
    } catch (const raymatch::Error& e) {
      raise(*error_type, e, nullptr);
    }
  });

  rp::BindScene(m);
  rp::BindCompare(m);
  rp::BindCalibrate(m);
  rp::BindFit(m);
  rp::BindSensitivity(m);
}
