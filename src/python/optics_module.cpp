// mitsuba_powder._optics: the plugin's double-precision grain optics
// (src/bsdfs/powder_optics.h) exposed to Python, so that Python code and tests
// use the same implementation as the renderer.

#include <nanobind/nanobind.h>
#include <nanobind/stl/complex.h>
#include <nanobind/stl/pair.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/vector.h>

#include <optional>

#include "../bsdfs/powder_optics.h"

namespace nb = nanobind;

namespace {

powder::Mixing parse_mixing(const std::string &mixing) {
    if (mixing == "bruggeman")
        return powder::Mixing::Bruggeman;
    if (mixing == "maxwell_garnett")
        return powder::Mixing::MaxwellGarnett;
    powder::fail("mixing = \"", mixing, "\" is not valid; valid values are \"bruggeman\" and "
                 "\"maxwell_garnett\"");
}

void check_positive(const char *name, double v) {
    if (!(v > 0.0) || !std::isfinite(v))
        powder::fail(name, " = ", v, " is out of range; valid range is (0, inf)");
}

void check_fill(double f) {
    if (!(f > 0.0 && f <= 1.0))
        powder::fail("agglomerate_fill = ", f, " is out of range; valid range is (0, 1]");
}

/// rho per wavelength and its derivatives [d radius, d radius2, d fraction2,
/// d agglomerate_radius, d agglomerate_fill] (the plugin's albedo table, in double)
std::pair<std::vector<double>, std::vector<std::vector<double>>>
albedo_table(const std::string &grains, const std::vector<double> &wavelengths_nm,
             const std::vector<std::complex<double>> &index, double radius,
             std::optional<double> radius2, std::optional<double> fraction2,
             std::optional<double> agglomerate_radius, double agglomerate_fill,
             const std::string &mixing, bool derivatives) {
    powder::Grains g{ radius };
    if (grains == "sphere")
        g.model = powder::GrainModel::Sphere;
    else if (grains == "agglomerate")
        g.model = powder::GrainModel::Agglomerate;
    else if (grains == "slab")
        g.model = powder::GrainModel::Slab;
    else
        powder::fail("grains = \"", grains, "\" is not valid; valid values are \"sphere\", "
                     "\"agglomerate\" and \"slab\"");
    if (wavelengths_nm.size() != index.size())
        powder::fail("wavelengths_nm and index differ in length (", wavelengths_nm.size(),
                     " and ", index.size(), ")");
    check_positive("radius", radius);
    if (radius2.has_value() != fraction2.has_value())
        powder::fail("a second grain population needs both radius2 and fraction2");
    if (radius2) {
        if (g.model == powder::GrainModel::Agglomerate)
            powder::fail("radius2 cannot be used with grains = \"agglomerate\" (one "
                         "population)");
        check_positive("radius2", *radius2);
        if (!(*fraction2 >= 0.0 && *fraction2 <= 1.0))
            powder::fail("fraction2 = ", *fraction2, " is out of range; valid range is [0, 1]");
        g.two = true;
        g.r2 = *radius2;
        g.f2 = *fraction2;
    }
    if (g.model == powder::GrainModel::Agglomerate) {
        if (!agglomerate_radius)
            powder::fail("grains = \"agglomerate\" needs agglomerate_radius (um); valid range "
                         "is (0, inf)");
        check_positive("agglomerate_radius", *agglomerate_radius);
        check_fill(agglomerate_fill);
        g.agglomerate_radius = *agglomerate_radius;
        g.agglomerate_fill = agglomerate_fill;
        g.mixing = parse_mixing(mixing);
    } else if (agglomerate_radius) {
        powder::fail("agglomerate_radius is used only with grains = \"agglomerate\"");
    }
    for (double wl : wavelengths_nm)
        check_positive("wavelength (nm)", wl);
    std::vector<powder::AlbedoRow> rows =
        powder::albedo_table(g, wavelengths_nm, index, derivatives);
    std::vector<double> rho;
    std::vector<std::vector<double>> d;
    for (const powder::AlbedoRow &r : rows) {
        rho.push_back(r.rho);
        d.push_back({ r.d_r1, r.d_r2, r.d_f2, r.d_ra, r.d_fill });
    }
    return { rho, d };
}

} // namespace

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

    m.def("effective_index",
          [](std::complex<double> index, double fill, const std::string &mixing) {
              check_fill(fill);
              return powder::effective_index(index, fill, parse_mixing(mixing));
          },
          nb::arg("index"), nb::arg("fill"), nb::arg("mixing") = "bruggeman",
          "Effective index sqrt(eps) of crystallites of index n + ik packed at volume fill "
          "`fill` in air, by the rule `mixing` (\"bruggeman\" or \"maxwell_garnett\").");

    m.def("slab_albedo",
          [](std::complex<double> index, double diameter_um, double wavelength_um) {
              if (!(index.real() > 1.0))
                  powder::fail("n = ", index.real(), " is out of range; Hapke's slab needs "
                               "n > 1 (valid range (1, inf))");
              check_positive("diameter_um", diameter_um);
              check_positive("wavelength_um", wavelength_um);
              return powder::slab_albedo(index, diameter_um, wavelength_um).first;
          },
          nb::arg("index"), nb::arg("diameter_um"), nb::arg("wavelength_um"),
          "Hapke's equivalent-slab albedo of grains of size D (um) and index n + ik (n > 1) "
          "at a wavelength in um.");

    m.def("albedo_table", &albedo_table, nb::arg("grains"), nb::arg("wavelengths_nm"),
          nb::arg("index"), nb::arg("radius"), nb::arg("radius2") = nb::none(),
          nb::arg("fraction2") = nb::none(), nb::arg("agglomerate_radius") = nb::none(),
          nb::arg("agglomerate_fill") = 0.5, nb::arg("mixing") = "bruggeman",
          nb::arg("derivatives") = false,
          "The plugin's albedo table in double precision: (rho per wavelength, per wavelength "
          "[d/d radius, d/d radius2, d/d fraction2, d/d agglomerate_radius, "
          "d/d agglomerate_fill]) for grains = \"sphere\", \"agglomerate\" or \"slab\" "
          "(docs/model.md, \"Grain models\"); radii in um, wavelengths in nm, index n + ik per "
          "wavelength.");

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
