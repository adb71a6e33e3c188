// mitsuba_powder._optics: the plugin's double-precision grain optics
// (src/bsdfs/powder_optics.h) exposed to Python, so that Python code and tests
// use the same implementation as the renderer.

#include <nanobind/nanobind.h>
#include <nanobind/stl/complex.h>
#include <nanobind/stl/pair.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#include "../bsdfs/powder_optics.h"

namespace nb = nanobind;

NB_MODULE(_optics, m) {
    m.doc() = "Grain optics of the powder BSDF (double precision, same code as the plugin)";

    m.def("mie_efficiencies",
          [](std::complex<double> index, double x) {
              if (!(x > 0.0))
                  powder::fail("x = ", x, " is out of range; valid range is (0, inf)");
              powder::MieEfficiencies q = powder::mie_efficiencies(index, x);
              return std::make_pair(q.q_ext, q.q_sca);
          },
          nb::arg("index"), nb::arg("x"),
          "(Q_ext, Q_sca) of a sphere of relative index n + ik (k >= 0 absorbs) and size "
          "parameter x = 2 pi r / lambda.");

    m.def("tau_o_fresnel",
          [](double n) {
              if (!(n > 0.0))
                  powder::fail("n = ", n, " is out of range; valid range is (0, inf)");
              return powder::tau_o_fresnel(n);
          },
          nb::arg("n"),
          "Extrapolation ratio tau_o from the Fresnel reflectance of a grain of real index n.");

    m.def("load_optical_constants",
          [](const std::string &path) {
              powder::OpticalTable t = powder::load_refractiveindex_yaml(path);
              return std::make_tuple(t.wavelength_um, t.n, t.k);
          },
          nb::arg("path"),
          "(wavelength_um, n, k) lists from a refractiveindex.info YAML file (strict loader).");

    m.def("hematite_average",
          [](const std::string &path_o, const std::string &path_e) {
              powder::OpticalTable t = powder::orientation_average(
                  powder::load_refractiveindex_yaml(path_o),
                  powder::load_refractiveindex_yaml(path_e));
              return std::make_tuple(t.wavelength_um, t.n, t.k);
          },
          nb::arg("path_o"), nb::arg("path_e"),
          "Orientation average (2 o + e) / 3 of the ordinary and extraordinary tables.");
}
