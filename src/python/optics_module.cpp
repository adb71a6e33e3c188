// mitsuba_powder._optics: the plugin's double-precision grain optics
// (src/bsdfs/powder_optics.h) exposed to Python, so that Python code and tests
// use the same implementation as the renderer.

#include <nanobind/nanobind.h>
#include <nanobind/stl/complex.h>
#include <nanobind/stl/pair.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/map.h>
#include <nanobind/stl/variant.h>
#include <nanobind/stl/vector.h>

#include <cmath>
#include <map>
#include <optional>
#include <variant>

#include "../bsdfs/powder_optics.h"

namespace nb = nanobind;

namespace {

powder::Mixing parse_mixing(const std::string &mixing) {
    return (powder::Mixing) powder_param::choice_index("mixing", mixing);
}

/// The plugin's range check of a numeric property (powder_registry.h)
void check(const char *name, double v) {
    powder_param::Id p = powder_param::find(name);
    const powder_param::Range &r = powder_param::Table[p].range;
    if (!r.contains(v))
        powder::fail(name, " = ", v, " is out of range; valid range is ", r.str());
}

void check_positive(const char *name, double v) {
    if (!(v > 0.0) || !std::isfinite(v))
        powder::fail(name, " = ", v, " is out of range; valid range is (0, inf)");
}

/// rho per wavelength and its derivatives [d radius, d radius2, d fraction2,
/// d agglomerate_radius, d agglomerate_fill] (the plugin's albedo table, in double)
std::pair<std::vector<double>, std::vector<std::vector<double>>>
albedo_table(const std::string &grains, const std::vector<double> &wavelengths_nm,
             const std::vector<std::complex<double>> &index, double radius,
             std::optional<double> radius2, std::optional<double> fraction2,
             std::optional<double> agglomerate_radius, double agglomerate_fill,
             const std::string &mixing, bool derivatives) {
    powder::Grains g;
    g.r[0] = radius;
    size_t model = powder_param::choice_index("grains", grains);
    g.model = (powder::GrainModel) model;
    if (wavelengths_nm.size() != index.size())
        powder::fail("wavelengths_nm and index differ in length (", wavelengths_nm.size(),
                     " and ", index.size(), ")");
    // the plugin's rules of the grain model (agglomerate_fill and mixing have defaults here)
    powder_param::check_grain_properties(
        model,
        [&](const char *name) {
            std::string n = name;
            return n == "radius" || (n == "radius2" && radius2) ||
                   (n == "fraction2" && fraction2) ||
                   (n == "agglomerate_radius" && agglomerate_radius);
        },
        false);
    check("radius", radius);
    if (radius2) {
        check("radius2", *radius2);
        check("fraction2", *fraction2);
        g.populations = 2;
        g.r[1] = *radius2;
        g.set_fractions({ 1.0, *fraction2, 0.0, 0.0 });
    }
    if (g.model == powder::GrainModel::Agglomerate) {
        check("agglomerate_radius", *agglomerate_radius);
        check("agglomerate_fill", agglomerate_fill);
        g.agglomerate_radius = *agglomerate_radius;
        g.agglomerate_fill = agglomerate_fill;
        g.mixing = parse_mixing(mixing);
    }
    for (double wl : wavelengths_nm)
        check_positive("wavelength (nm)", wl);
    std::vector<powder::PopulationIndex> pindex;
    for (const auto &m : index)
        pindex.push_back({ m, m, m, m });
    std::vector<powder::AlbedoRow> rows =
        powder::albedo_table(g, wavelengths_nm, pindex, derivatives);
    std::vector<double> rho;
    std::vector<std::vector<double>> d;
    using namespace powder_param;
    for (const powder::AlbedoRow &r : rows) {
        rho.push_back(r.rho);
        d.push_back({ r.d[Radius], r.d[Radius2], r.d[Fraction2], r.d[AgglomerateRadius],
                      r.d[AgglomerateFill] });
    }
    return { rho, d };
}

/// The albedo of a mixture of populations (radius, fraction, index per wavelength), the
/// first population's fraction None (1 - the others): rho per wavelength and per
/// wavelength [d r1, d r2, d f2, ...] (docs/model.md, "Several materials")
std::pair<std::vector<double>, std::vector<std::vector<double>>>
mixture_albedo(const std::string &grains, const std::vector<double> &wavelengths_nm,
               const std::vector<std::tuple<double, std::optional<double>,
                                            std::vector<std::complex<double>>>> &populations,
               bool derivatives) {
    using namespace powder_param;
    size_t model = choice_index("grains", grains);
    if (model == 1)
        powder::fail("grains = \"agglomerate\" has one population; use albedo_table");
    if (populations.empty() || populations.size() > MaxPopulations)
        powder::fail("populations: ", populations.size(), " given; valid range is [1, ",
                     MaxPopulations, "]");
    powder::Grains g;
    g.model = (powder::GrainModel) model;
    g.populations = populations.size();
    std::array<double, MaxPopulations> f{ 1.0, 0.0, 0.0, 0.0 };
    double sum = 0.0;
    for (size_t j = 0; j < populations.size(); ++j) {
        auto &[r, fj, idx] = populations[j];
        check(Table[PopulationRadius[j]].name, r);
        if (j == 0 && fj)
            powder::fail("the fraction of population 1 is 1 - the others: give None");
        if (j > 0) {
            if (!fj)
                powder::fail("population ", j + 1, " needs a fraction");
            check(Table[PopulationFraction[j]].name, *fj);
            f[j] = *fj;
            sum += *fj;
        }
        if (idx.size() != wavelengths_nm.size())
            powder::fail("population ", j + 1, ": ", idx.size(), " indices for ",
                         wavelengths_nm.size(), " wavelengths");
        g.r[j] = r;
    }
    if (!(sum <= 1.0 + 1e-6))
        powder::fail("the fractions of populations 2..", populations.size(), " sum to ", sum,
                     "; valid range of their sum is [0, 1]");
    g.set_fractions(f);
    for (double wl : wavelengths_nm)
        check_positive("wavelength (nm)", wl);
    std::vector<powder::PopulationIndex> pindex(wavelengths_nm.size());
    for (size_t i = 0; i < wavelengths_nm.size(); ++i)
        for (size_t j = 0; j < MaxPopulations; ++j)
            pindex[i][j] = std::get<2>(populations[std::min(j, populations.size() - 1)])[i];
    std::vector<powder::AlbedoRow> rows =
        powder::albedo_table(g, wavelengths_nm, pindex, derivatives);
    std::vector<double> rho;
    std::vector<std::vector<double>> d;
    for (const powder::AlbedoRow &r : rows) {
        rho.push_back(r.rho);
        std::vector<double> dj{ r.d[Radius] };
        for (size_t j = 1; j < populations.size(); ++j) {
            dj.push_back(r.d[PopulationRadius[j]]);
            dj.push_back(r.d[PopulationFraction[j]]);
        }
        d.push_back(dj);
    }
    return { rho, d };
}

std::vector<std::string> materials() {
    std::vector<std::string> out;
    for (const powder_param::Material &m : powder_param::Materials)
        out.push_back(m.name);
    return out;
}

std::map<std::string, double> material_densities() {
    std::map<std::string, double> out;
    for (const powder_param::Material &m : powder_param::Materials)
        out[m.name] = m.density;
    return out;
}

std::map<std::string, std::vector<std::string>> material_files() {
    std::map<std::string, std::vector<std::string>> out;
    for (const powder_param::Material &m : powder_param::Materials)
        for (const char *f : m.files)
            if (f)
                out[m.name].push_back(f);
    return out;
}

std::map<std::string, std::variant<double, std::string>> property_defaults() {
    using namespace powder_param;
    std::map<std::string, std::variant<double, std::string>> out;
    for (size_t i = 0; i < Count; ++i)
        if (has_default((Id) i))
            out[Table[i].name] = Table[i].def;
    for (const Number &n : Numbers)
        if (!std::isnan(n.def))
            out[n.name] = n.def;
    for (const Choice &c : ChoiceTable)
        out[c.name] = std::string(c.values[0]);
    for (const Text &t : Texts)
        out[t.name] = std::string(t.def);
    return out;
}

/// f(range) of every numeric property
template <typename F> auto per_range(F f) {
    std::map<std::string, decltype(f(powder_param::Table[0].range))> out;
    for (const powder_param::Spec &s : powder_param::Table)
        out[s.name] = f(s.range);
    for (const powder_param::Number &n : powder_param::Numbers)
        out[n.name] = f(n.range);
    return out;
}

std::map<std::string, std::pair<double, double>> property_ranges() {
    return per_range([](const powder_param::Range &r) { return std::pair{ r.lo, r.hi }; });
}

std::map<std::string, std::pair<bool, bool>> property_range_ends() {
    return per_range(
        [](const powder_param::Range &r) { return std::pair{ r.lo_closed, r.hi_closed }; });
}

/// Every numeric property's valid range with its ends, (lo, hi, lo closed, hi closed): the
/// Range of powder_registry.h whole, as the plugin's checks read it (Range::contains
/// compares closed ends in single precision)
std::map<std::string, std::tuple<double, double, bool, bool>> property_intervals() {
    return per_range([](const powder_param::Range &r) {
        return std::tuple{ r.lo, r.hi, r.lo_closed, r.hi_closed };
    });
}

nb::dict grain_models() {
    using namespace powder_param;
    nb::dict out;
    const Choice &grains = ChoiceTable[Grains];
    for (size_t m = 0; m < grains.count; ++m) {
        const GrainRule &rule = GrainRules[m];
        nb::list allowed, required;
        for (const char *a : rule.allowed)
            if (a)
                allowed.append(a);
        if (rule.required)
            required.append(rule.required);
        nb::dict d;
        d["size"] = Table[rule.size].name;
        d["allowed"] = allowed;
        d["required"] = required;
        d["two_populations"] = rule.two_populations;
        out[grains.values[m]] = d;
    }
    return out;
}

/// The grain optics of powder_optics.h
void def_optics(nb::module_ &m) {
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
              check("agglomerate_fill", fill);
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
}

/// The albedo table and the optical constants
void def_tables(nb::module_ &m) {
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

    m.def("mixture_albedo", &mixture_albedo, nb::arg("grains"), nb::arg("wavelengths_nm"),
          nb::arg("populations"), nb::arg("derivatives") = false,
          "The plugin's albedo of several grain populations of their own materials "
          "(docs/model.md, \"Several materials\"): populations = [(radius um, fraction, index "
          "n + ik per wavelength), ...], the first fraction None (1 - the others); returns "
          "(rho per wavelength, per wavelength [d/d radius, d/d radius2, d/d fraction2, ...]).");

    m.def("bruggeman_mixture",
          [](const std::vector<std::complex<double>> &index, const std::vector<double> &f) {
              if (index.size() != f.size() || index.empty())
                  powder::fail("index and fractions differ in length or are empty (",
                               index.size(), " and ", f.size(), ")");
              double sum = 0.0;
              for (double v : f) {
                  if (!(v >= 0.0 && v <= 1.0))
                      powder::fail("fraction = ", v, " is out of range; valid range is [0, 1]");
                  sum += v;
              }
              if (!(std::abs(sum - 1.0) <= 1e-6))
                  powder::fail("the fractions sum to ", sum, "; they must sum to 1");
              return powder::bruggeman_mixture(index, f);
          },
          nb::arg("index"), nb::arg("fractions"),
          "Bruggeman effective index of materials of indices n + ik at volume fractions "
          "summing to 1 (the index tau_o of a mixture comes from).");

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

/// The plugin's properties (powder_registry.h): what Python reads instead of its own copy
void def_registry(nb::module_ &m) {
    m.def("materials", &materials, "Names of the built-in grain materials (property \"material\").");
    m.def("material_densities", &material_densities,
          "Density (g/cm^3) of each built-in material: converts mass to volume fractions.");
    m.def("material_files", &material_files,
          "Optical-constant files of each built-in material, relative to the package's folder "
          "(two files: the ordinary and extraordinary rays, averaged (2 o + e) / 3).");
    m.def("property_defaults", &property_defaults,
          "Every property of the plugin that has a default, with it (float or str).");
    m.def("property_ranges", &property_ranges,
          "Valid (lo, hi) of the numeric properties as the plugin checks them; "
          "property_range_ends gives which ends are closed.");
    m.def("property_range_ends", &property_range_ends,
          "Whether the (lo, hi) ends of each range of property_ranges are closed.");
    m.def("property_intervals", &property_intervals,
          "{property: (lo, hi, lo closed, hi closed)}: the valid range of every numeric "
          "property, with its ends, as the plugin checks it.");
    m.def("grain_models", &grain_models,
          "Per grain model (\"sphere\", \"agglomerate\", \"slab\"): \"size\" (the property "
          "of the first population's size), \"allowed\" and \"required\" (grain properties), "
          "\"two_populations\" (whether radius2 and fraction2 are allowed).");
}

} // namespace

NB_MODULE(_optics, m) {
    m.doc() = "Grain optics of the powder BSDF (double precision, same code as the plugin), "
              "and the plugin's property registry";
    def_optics(m);
    def_tables(m);
    def_registry(m);
}
