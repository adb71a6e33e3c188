#pragma once

/*
 * The properties of the `powder` plugin in one place: the float parameters (default,
 * range, differentiable), the other numeric properties, the string properties and their
 * values, the built-in materials and the grain models with the properties each allows and
 * requires (docs/model.md, "Grain models"). The plugin's parsing and validation read these
 * tables, and so does the Python module mitsuba_powder._optics, which exposes them to the
 * Python package; so this header has no Mitsuba or Dr.Jit dependency.
 */

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

namespace powder {

/// Raise std::runtime_error with the streamed arguments as message
template <typename... Args> [[noreturn]] void fail(const Args &...args) {
    std::ostringstream oss;
    (oss << ... << args);
    throw std::runtime_error(oss.str());
}

} // namespace powder

namespace powder_param {

constexpr double Inf = std::numeric_limits<double>::infinity();

/// The wavelength grid of spectral variants' tables: TableSize nodes TableStep nm apart from
/// TableMin nm (360..830 nm, the range of Mitsuba's spectral variants)
inline constexpr int TableSize = 471;
inline constexpr float TableMin = 360.f, TableStep = 1.f;

/// Valid values of a parameter: an interval with open or closed ends
struct Range {
    double lo, hi;
    bool lo_closed, hi_closed;

    /// Closed ends are compared in single precision: the plugin stores floats,
    /// and so may the caller (e.g. sigma = pi/2 rounded up)
    bool contains(double v) const {
        float vf = (float) v;
        return !std::isnan(v) && (lo_closed ? vf >= (float) lo : v > lo) &&
               (hi_closed ? vf <= (float) hi : v < hi);
    }

    /// The interval as written in the errors and docs, e.g. "(0, inf)"
    std::string str() const {
        std::ostringstream oss;
        oss << (lo_closed ? "[" : "(") << lo << ", " << hi << (hi_closed ? "]" : ")");
        return oss.str();
    }
};

/// The message for a value outside its range ("" inside it)
inline std::string range_error(const char *name, double value, const Range &r) {
    if (r.contains(value))
        return "";
    std::ostringstream oss;
    oss << "property \"" << name << "\" = " << value << " is out of range; valid range is "
        << r.str();
    return oss.str();
}

/**
 * The float parameters of the model (docs/model.md, "Parameters"). One row each drives
 * reading the property (default, range), the range check after an edit through
 * mi.traverse (parameters_changed), the traversal key and whether it is
 * differentiable; tests/plugin/test_params_doc.py checks that the doc comment above the
 * class and docs/powder.md list the same names, defaults and ranges.
 *
 * The ranges are those over which eval, pdf and sample are finite for every combination of
 * accepted values (docs/model.md, "Valid ranges"; tests/plugin/test_finite.py): each
 * finite end is the limit measured with the other properties at their worst ends, rounded
 * inwards to a power of ten, where that limit is not a physical one.
 */
struct Spec {
    const char *name;
    const char *unit;     ///< "-" when dimensionless
    double def;           ///< value held when the property is absent
    const char *def_doc;  ///< the default as documented
    Range range;
    bool fittable;        ///< differentiable and exposed by mi.traverse
};

enum Id : size_t {
    AmplitudeVolume, G, Extinction, TauO, Thickness, AmplitudeSurface, CorrelationLength,
    Sigma, Radius, Radius2, Fraction2, AgglomerateRadius, AgglomerateFill, Radius3, Fraction3,
    Radius4, Fraction4, Count
};

/// Grain populations (docs/model.md, "Several materials"): population j (0-based here, j + 1
/// in the property names) has the radius PopulationRadius[j] and, for j >= 1, the volume
/// fraction PopulationFraction[j] (population 1 gets 1 - the others)
inline constexpr size_t MaxPopulations = 4;
inline constexpr Id PopulationRadius[MaxPopulations] = { Radius, Radius2, Radius3, Radius4 };
inline constexpr Id PopulationFraction[MaxPopulations] = { Count, Fraction2, Fraction3,
                                                           Fraction4 };
/// The material properties of each population ("material{j}", "eta{j}", "k{j}")
inline constexpr const char *PopulationMaterial[MaxPopulations] = { "material", "material2",
                                                                    "material3", "material4" };
inline constexpr const char *PopulationEta[MaxPopulations] = { "eta", "eta2", "eta3", "eta4" };
inline constexpr const char *PopulationK[MaxPopulations] = { "k", "k2", "k3", "k4" };

inline constexpr Spec Table[Count] = {
    // name                 unit    default  default as documented
    //     range {lo, hi, lo closed, hi closed}, fittable
    { "amplitude_volume",   "-",    1.0,     "1.0",
          { 0.0, 1e16, true, true }, true },
    { "g",                  "-",    0.0,     "0.0",
          { -1.0, 1.0, false, false }, true },
    { "extinction",         "1/um", 1.0,     "1.0",
          { 1e-8, Inf, true, false }, true },
    { "tau_o",              "-",    2.0 / 3, "from Fresnel of Re(eta)",
          { 0.0, 1e20, true, true }, true },
    { "thickness",          "um",   Inf,     "infinite",
          { 0.0, Inf, true, true }, true },
    { "amplitude_surface",  "um^2", 0.0,     "0.0",
          { 0.0, 1e6, true, true }, true },
    { "correlation_length", "um",   1.0,     "1.0",
          { 0.0, 1e8, false, true }, true },
    { "sigma",              "rad",  0.1,     "0.1",
          { 1e-18, 0.5 * M_PI, true, true }, true },
    { "radius",             "um",   0.017,   "0.017",
          { 0.0, Inf, false, false }, true },
    { "radius2",            "um",   1.0,     "none (one population)",
          { 0.0, Inf, false, false }, true },
    { "fraction2",          "-",    0.0,     "none (one population)",
          { 0.0, 1.0, true, true }, true },
    { "agglomerate_radius", "um",   1.0,     "none (required with agglomerates)",
          { 0.0, Inf, false, false }, true },
    { "agglomerate_fill",   "-",    0.5,     "0.5",
          { 1e-6, 1.0, true, true }, true },
    { "radius3",            "um",   1.0,     "none (no third population)",
          { 0.0, Inf, false, false }, true },
    { "fraction3",          "-",    0.0,     "none (no third population)",
          { 0.0, 1.0, true, true }, true },
    { "radius4",            "um",   1.0,     "none (no fourth population)",
          { 0.0, Inf, false, false }, true },
    { "fraction4",          "-",    0.0,     "none (no fourth population)",
          { 0.0, 1.0, true, true }, true },
};

/// Whether a float parameter has a default: the others are computed (tau_o) or absent
/// unless given (the second population, the agglomerate radius)
constexpr bool has_default(Id p) {
    return p != TauO && p != Radius2 && p != Fraction2 && p != AgglomerateRadius &&
           p != Radius3 && p != Fraction3 && p != Radius4 && p != Fraction4;
}

/// The float parameter of a name (Count if none)
inline Id find(const char *name) {
    for (size_t i = 0; i < Count; ++i)
        if (std::strcmp(Table[i].name, name) == 0)
            return (Id) i;
    return Count;
}

/// Whether a parameter describes the grains (it sets the Mie / grain tables)
constexpr bool is_grain_param(Id p) {
    return p == Radius || p == Radius2 || p == Fraction2 || p == AgglomerateRadius ||
           p == AgglomerateFill || p == Radius3 || p == Fraction3 || p == Radius4 ||
           p == Fraction4;
}

/// The parameters the normalisation of energy = "conserving" is tabulated from (one value
/// each: no texture, no value per lane)
constexpr bool is_normalisation_param(Id p) {
    return p == AmplitudeVolume || p == G || p == Extinction || p == TauO || p == Thickness ||
           is_grain_param(p);
}

/// The other numeric properties (not traversed): one value, or a spectrum (eta, k). Their
/// ranges hold every wavelength (`wavelength`, each of `rgb_wavelengths`) and every value of
/// an optical-constant table (eta and k, or n and k of a material file; docs/model.md,
/// "Valid ranges")
struct Number {
    const char *name;
    double def; ///< NaN: no default
    Range range;
};

inline constexpr Number Numbers[] = {
    { "wavelength", 700.0, { 1.0, 1e6, true, true } },
    { "eta", std::numeric_limits<double>::quiet_NaN(), { 1e-3, 1e3, true, true } },
    { "k", std::numeric_limits<double>::quiet_NaN(), { 0.0, 1e3, true, true } },
};
inline constexpr const Number &WavelengthNumber = Numbers[0], &EtaNumber = Numbers[1],
                              &KNumber = Numbers[2];

/// The values of the string properties with a fixed set of values, the first the default
inline constexpr std::array<const char *, 3> GrainValues = { "sphere", "agglomerate", "slab" };
inline constexpr std::array<const char *, 2> MixingValues = { "bruggeman", "maxwell_garnett" },
    SpecularValues = { "harvey_shack", "gaussian" }, SurfaceFresnelValues = { "none", "fresnel" },
    SamplingValues = { "lobes", "cosine" }, EnergyValues = { "paper", "conserving" };

struct Choice {
    const char *name;
    const char *const *values;
    size_t count;
};

enum ChoiceId : size_t { Grains, Mixing, Specular, SurfaceFresnel, Sampling, Energy, Choices };

inline constexpr Choice ChoiceTable[Choices] = {
    { "grains", GrainValues.data(), GrainValues.size() },
    { "mixing", MixingValues.data(), MixingValues.size() },
    { "specular", SpecularValues.data(), SpecularValues.size() },
    { "surface_fresnel", SurfaceFresnelValues.data(), SurfaceFresnelValues.size() },
    { "sampling", SamplingValues.data(), SamplingValues.size() },
    { "energy", EnergyValues.data(), EnergyValues.size() },
};

/// "\"a\", \"b\" and \"c\"": the valid values of a choice, for errors
inline std::string valid_values(const Choice &c) {
    std::string valid;
    for (size_t i = 0; i < c.count; ++i)
        valid += std::string(i ? (i + 1 == c.count ? " and " : ", ") : "") + "\"" +
                 c.values[i] + "\"";
    return valid;
}

/// Index of `value` among the values of the choice `name`; throws the project's error
/// naming the property, the value and the valid values otherwise
inline size_t choice_index(const char *name, const std::string &value) {
    for (const Choice &c : ChoiceTable) {
        if (std::strcmp(c.name, name) != 0)
            continue;
        for (size_t i = 0; i < c.count; ++i)
            if (value == c.values[i])
                return i;
        powder::fail("powder: property \"", name, "\" = \"", value,
                     "\" is not valid; valid values are ", valid_values(c));
    }
    powder::fail("powder: \"", name, "\" is not a property with a fixed set of values");
}

/// Free-form string properties and their defaults
struct Text {
    const char *name, *def;
};

inline constexpr Text Texts[] = {
    { "lobes", "all" },
    { "material", "hematite" },
    { "rgb_wavelengths", "611.3, 549.1, 464.3" },
};
inline constexpr const Text &LobeList = Texts[0], &MaterialName = Texts[1],
                            &RgbWavelengths = Texts[2];

/// A built-in material: its optical-constant files (refractiveindex.info YAML, relative
/// to the package's folder on Mitsuba's file resolver) and how it is described. Two files
/// are the ordinary and extraordinary rays of a uniaxial crystal, averaged (2 o + e) / 3.
struct Material {
    const char *name;
    std::array<const char *, 2> files;
    const char *source;
    double density; ///< g/cm^3 (Handbook of Mineralogy, measured): mass to volume fractions
};

inline constexpr Material Materials[] = {
    { "hematite",
      { "data/optical_constants/hematite_Querry-o.yml",
        "data/optical_constants/hematite_Querry-e.yml" },
      "hematite (Querry 1985, orientation average of o and e rays)", 5.26 },
    { "magnetite", { "data/optical_constants/magnetite_Querry.yml", nullptr },
      "magnetite (Querry 1985)", 5.18 },
    { "calcite",
      { "data/optical_constants/calcite_Ghosh-o.yml",
        "data/optical_constants/calcite_Ghosh-e.yml" },
      "calcite (Ghosh 1999, orientation average of o and e rays)", 2.71 },
    { "quartz",
      { "data/optical_constants/quartz_Ghosh-o.yml",
        "data/optical_constants/quartz_Ghosh-e.yml" },
      "quartz (Ghosh 1999, orientation average of o and e rays)", 2.65 },
    { "rutile",
      { "data/optical_constants/rutile_Devore-o.yml",
        "data/optical_constants/rutile_Devore-e.yml" },
      "rutile (Devore 1951, orientation average of o and e rays)", 4.25 },
    { "kaolinite", { "data/optical_constants/kaolinite_constant.yml", nullptr },
      "kaolinite (constant index 1.564, Handbook of Mineralogy)", 2.63 },
    { "gypsum", { "data/optical_constants/gypsum_constant.yml", nullptr },
      "gypsum (constant index 1.524, Handbook of Mineralogy)", 2.31 },
};

/// The built-in material of a name (nullptr if none)
inline const Material *find_material(const std::string &name) {
    for (const Material &m : Materials)
        if (name == m.name)
            return &m;
    return nullptr;
}

/// The properties of the populations 2..4 (allowed by grain models with several populations)
inline constexpr std::array<const char *, 15> PopulationProperties = {
    "radius2", "fraction2", "material2", "eta2", "k2", "radius3", "fraction3", "material3",
    "eta3", "k3", "radius4", "fraction4", "material4", "eta4", "k4"
};

/// The properties that describe the grains; which of them a grain model allows is its rule
/// (and PopulationProperties, with several populations)
inline constexpr std::array<const char *, 6> GrainProperties = {
    "radius", "radius2", "fraction2", "agglomerate_radius", "agglomerate_fill", "mixing"
};

/// The properties a given `albedo` replaces (an error together with it): the grain model
/// and every property of the grains (and PopulationProperties)
inline constexpr std::array<const char *, 7> AlbedoExcludes = {
    "grains", "radius", "radius2", "fraction2", "agglomerate_radius", "agglomerate_fill", "mixing"
};

/// Whether a property is one of populations 2..4
inline bool is_population_property(const char *name) {
    for (const char *a : PopulationProperties)
        if (std::strcmp(a, name) == 0)
            return true;
    return false;
}

/// A grain model (a value of `grains`, in the order of ChoiceTable[Grains]): the parameter
/// that is its (first) population's size, the grain properties it allows and requires,
/// and whether it allows populations 2..4 (PopulationProperties)
struct GrainRule {
    Id size;
    std::array<const char *, 4> allowed; ///< nullptr-padded
    const char *required;                ///< nullptr: none
    bool two_populations;

    bool allows(const char *name) const {
        if (two_populations && is_population_property(name))
            return true;
        for (const char *a : allowed)
            if (a && std::strcmp(a, name) == 0)
                return true;
        return false;
    }
};

inline constexpr GrainRule GrainRules[3] = {
    { Radius, { "radius", "radius2", "fraction2", nullptr }, nullptr, true },
    { AgglomerateRadius, { "radius", "agglomerate_radius", "agglomerate_fill", "mixing" },
      "agglomerate_radius", false },
    { Radius, { "radius", "radius2", "fraction2", nullptr }, nullptr, true },
};

/**
 * Check the grain properties given (has(name)) against the rules of grain model `model`
 * (an index of ChoiceTable[Grains]), with or without a given albedo; throws the
 * project's error naming the property and the models it is valid with.
 */
template <typename Has> void check_grain_properties(size_t model, const Has &has, bool albedo) {
    const Choice &grains = ChoiceTable[Grains];
    if (albedo)
        for (const char *name : AlbedoExcludes)
            if (name && has(name))
                powder::fail("powder: property \"", name, "\" has no effect together with "
                             "\"albedo\" (a given albedo replaces the one computed from the "
                             "grains); give one or the other");
    if (albedo)
        for (const char *name : PopulationProperties)
            if (has(name))
                powder::fail("powder: property \"", name, "\" has no effect together with "
                             "\"albedo\" (a given albedo replaces the one computed from the "
                             "grains); give one or the other");
    const GrainRule &rule = GrainRules[model];
    std::array<const char *, GrainProperties.size() + PopulationProperties.size()> names{};
    std::copy(GrainProperties.begin(), GrainProperties.end(), names.begin());
    std::copy(PopulationProperties.begin(), PopulationProperties.end(),
              names.begin() + GrainProperties.size());
    for (const char *name : names) {
        if (!name || !has(name) || rule.allows(name))
            continue;
        std::string valid;
        size_t n = 0;
        for (size_t m = 0; m < grains.count; ++m)
            if (GrainRules[m].allows(name))
                valid += std::string(n++ ? " or " : "") + "\"" + grains.values[m] + "\"";
        powder::fail("powder: property \"", name, "\" cannot be used with grains = \"",
                     grains.values[model], "\"", rule.two_populations ? "" : " (one population)",
                     "; it is used only with grains = ", valid);
    }
    if (!albedo && rule.required && !has(rule.required))
        powder::fail("powder: grains = \"", grains.values[model], "\" needs property \"",
                     rule.required, "\" (valid range is ", Table[find(rule.required)].range.str(),
                     ")");
    // populations 2..4: radius{j} and fraction{j} together, numbered without gaps, a
    // material only with its population, not both material{j} and eta{j}/k{j}
    for (size_t j = 1; j < MaxPopulations; ++j) {
        const char *r = Table[PopulationRadius[j]].name, *f = Table[PopulationFraction[j]].name;
        if (has(r) != has(f))
            powder::fail("powder: grain population ", j + 1, " needs both \"", r, "\" and \"",
                         f, "\"; got only \"", has(r) ? r : f, "\"");
        if (has(r) && j > 1 && !has(Table[PopulationRadius[j - 1]].name))
            powder::fail("powder: grain population ", j + 1, " (\"", r, "\") needs population ",
                         j, " (\"", Table[PopulationRadius[j - 1]].name, "\" and \"",
                         Table[PopulationFraction[j - 1]].name, "\"): populations are "
                         "numbered 2, 3, 4 without gaps");
        for (const char *m : { PopulationMaterial[j], PopulationEta[j], PopulationK[j] })
            if (has(m) && !has(r))
                powder::fail("powder: property \"", m, "\" describes grain population ", j + 1,
                             ", which needs \"", r, "\" and \"", f, "\"");
    }
}

} // namespace powder_param
