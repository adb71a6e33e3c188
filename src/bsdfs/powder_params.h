#pragma once

/*
 * The properties of the `powder` plugin: reading and checking them (the tables of
 * powder_registry.h: ranges, choices, the grain model's rules, the optical constants, the
 * lobes and wavelengths, the values texture-valued parameters hold), and PowderParams, the
 * part of the BSDF's state that holds them (a member of the BSDF, powder.cpp).
 */

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/string.h>
#include <mitsuba/render/texture.h>

#include <limits>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "powder_optics.h"
#include "powder_registry.h"
#include "powder_textures.h"

namespace powder_param {

using namespace mitsuba;

/// Throw the project's error for a value outside its range
inline void check_range(const char *name, double value, const Range &r) {
    if (std::string error = range_error(name, value, r); !error.empty())
        Throw("powder: %s", error);
}

/// Index of a string property's value among its `choices` (the first is the default)
template <size_t N>
size_t read_choice(const Properties &props, const char *name,
                   const std::array<const char *, N> &choices) {
    return choice_index(name, props.get<std::string>(name, choices[0]));
}

/// Smallest and largest value of a parameter over its lanes, and whether one is NaN:
/// a parameter set through mi.traverse may hold one value per lane (batched
/// evaluations, e.g. mitsuba_powder.rti_fit), and every lane must be checked
template <typename T> std::tuple<double, double, bool> lane_range(const T &v) {
    if constexpr (dr::is_jit_v<T>) {
        if (dr::width(v) > 1) {
            T d = dr::detach(v);
            return { (double) dr::slice(dr::min(d)), (double) dr::slice(dr::max(d)),
                     (bool) dr::slice(dr::any(dr::isnan(d))) };
        }
    }
    double x = (double) dr::slice(v);
    return { x, x, std::isnan(x) };
}

/// Check every lane of a parameter against its range (the project's error names the
/// first value out of range: the NaN, the smallest or the largest)
template <typename T> void check_lanes(Id p, const T &v) {
    auto [lo, hi, nan] = lane_range(v);
    const Spec &spec = Table[p];
    if (nan)
        check_range(spec.name, std::numeric_limits<double>::quiet_NaN(), spec.range);
    check_range(spec.name, lo, spec.range);
    check_range(spec.name, hi, spec.range);
}

/// Which terms are evaluated: the `lobes` property (and, per call, the BSDF context)
struct Lobes {
    bool single = false, multiple = false, coherent = false, surface = false;
    /// Whether some term is evaluated
    bool some() const { return single || multiple || coherent || surface; }
    /// Whether some volume term is evaluated
    bool volume() const { return single || multiple || coherent; }
};

/// Split a list at commas and white space
inline std::vector<std::string> tokenize(const std::string &s) {
    std::vector<std::string> out;
    std::string cur;
    for (char ch : s) {
        if (ch == ',' || ch == ' ' || ch == '\t' || ch == '\n') {
            if (!cur.empty())
                out.push_back(cur);
            cur.clear();
        } else {
            cur += ch;
        }
    }
    if (!cur.empty())
        out.push_back(cur);
    return out;
}

inline Lobes parse_lobes(const std::string &spec) {
    Lobes l;
    std::vector<std::string> names = tokenize(spec);
    if (names.empty())
        Throw("powder: property \"lobes\" = \"%s\" names no lobe; valid names "
              "are single, multiple, coherent, surface (or all)", spec);
    for (const std::string &n : names) {
        if (n == "all")
            l.single = l.multiple = l.coherent = l.surface = true;
        else if (n == "single")
            l.single = true;
        else if (n == "multiple")
            l.multiple = true;
        else if (n == "coherent")
            l.coherent = true;
        else if (n == "surface")
            l.surface = true;
        else
            Throw("powder: property \"lobes\" = \"%s\" contains the unknown lobe "
                  "\"%s\"; valid names are single, multiple, coherent, surface "
                  "(or all)", spec, n);
    }
    return l;
}

inline std::string lobes_string(const Lobes &l) {
    std::string out;
    for (auto [on, name] : { std::pair{ l.single, "single" }, std::pair{ l.multiple, "multiple" },
                             std::pair{ l.coherent, "coherent" },
                             std::pair{ l.surface, "surface" } })
        if (on)
            out += (out.empty() ? "" : ",") + std::string(name);
    return out;
}

/// The wavelengths in nm of the R, G, B channels of `rgb_wavelengths`
inline std::array<double, 3> parse_rgb_wavelengths(const std::string &spec) {
    std::vector<std::string> items = tokenize(spec);
    if (items.size() != 3)
        Throw("powder: property \"rgb_wavelengths\" = \"%s\" must hold exactly 3 "
              "wavelengths in nm (R, G, B), got %zu", spec, items.size());
    std::array<double, 3> out;
    for (size_t i = 0; i < 3; ++i) {
        char *end = nullptr;
        double v = std::strtod(items[i].c_str(), &end);
        if (end == items[i].c_str() || *end != '\0')
            Throw("powder: property \"rgb_wavelengths\" = \"%s\": \"%s\" is not a "
                  "number", spec, items[i]);
        if (!WavelengthNumber.range.contains(v))
            Throw("powder: property \"rgb_wavelengths\" = \"%s\": wavelength %g is "
                  "out of range; valid range is %s nm", spec, v, WavelengthNumber.range.str());
        out[i] = v;
    }
    return out;
}

/// `rgb_wavelengths`: a string, or a Python list / XML <vector>
inline std::array<double, 3> read_rgb_wavelengths(const Properties &props) {
    if (props.has_property("rgb_wavelengths") &&
        props.type("rgb_wavelengths") == Properties::Type::Vector) {
        auto v = props.get<Vector<double, 3>>("rgb_wavelengths");
        std::ostringstream oss;
        oss << v[0] << ", " << v[1] << ", " << v[2];
        return parse_rgb_wavelengths(oss.str());
    }
    return parse_rgb_wavelengths(props.get<std::string>("rgb_wavelengths", RgbWavelengths.def));
}

/// The grain model (`grains`, `mixing`), after checking the grain properties given
/// against its rules (powder_registry.h)
inline std::pair<powder::GrainModel, powder::Mixing> read_grain_model(const Properties &props) {
    size_t model = read_choice<3>(props, "grains", GrainValues);
    check_grain_properties(model, [&](const char *name) { return props.has_property(name); },
                           props.has_property("albedo"));
    size_t mixing = read_choice<2>(props, "mixing", MixingValues);
    return { (powder::GrainModel) model, (powder::Mixing) mixing };
}

/// (wavelengths in nm, values) of a float (or integer) or spectrum property; a uniform
/// value gets a wavelength list spanning every accepted wavelength
inline std::pair<std::vector<double>, std::vector<double>>
read_spectrum(const Properties &props, const char *name) {
    auto type = props.type(name);
    if (type == Properties::Type::Float || type == Properties::Type::Integer) {
        double v = props.get<double>(name);
        return { { WavelengthNumber.range.lo, WavelengthNumber.range.hi }, { v, v } };
    }
    if (type == Properties::Type::Spectrum) {
        Properties::Spectrum spec = props.get<Properties::Spectrum>(name);
        if (spec.is_uniform())
            return { { WavelengthNumber.range.lo, WavelengthNumber.range.hi },
                     { spec.values[0], spec.values[0] } };
        for (size_t i = 1; i < spec.wavelengths.size(); ++i)
            if (!(spec.wavelengths[i] > spec.wavelengths[i - 1]))
                Throw("powder: property \"%s\": wavelengths must increase (%g nm "
                      "after %g nm)", name, spec.wavelengths[i], spec.wavelengths[i - 1]);
        return { spec.wavelengths, spec.values };
    }
    Throw("powder: property \"%s\" must be a float or a spectrum of "
          "wavelength:value pairs (nm), e.g. <spectrum name=\"%s\" "
          "value=\"400:2.5, 700:2.9\"/>", name, name);
}

/// Optical constants of grain population j (0-based) from `eta{j}`/`k{j}` or
/// `material{j}` (a built-in name or a YAML file); population 1's default is hematite, and
/// a population j >= 2 without its own has none (it is made of population 1's material)
inline std::optional<powder::OpticalTable> load_optics(const Properties &props, size_t j = 0) {
    const char *eta = PopulationEta[j], *k = PopulationK[j], *mat = PopulationMaterial[j];
    bool has_eta = props.has_property(eta), has_k = props.has_property(k);
    if (has_eta || has_k) {
        if (!(has_eta && has_k))
            Throw("powder: give both \"%s\" and \"%s\" (got only \"%s\")", eta, k,
                  has_eta ? eta : k);
        if (props.has_property(mat))
            Throw("powder: give either \"%s\" or \"%s\" and \"%s\", not both", mat, eta, k);
        auto [wl_e, v_e] = read_spectrum(props, eta);
        auto [wl_k, v_k] = read_spectrum(props, k);
        for (double v : v_e)
            check_range(eta, v, EtaNumber.range);
        for (double v : v_k)
            check_range(k, v, KNumber.range);
        powder::OpticalTable t = powder::table_from_pairs(wl_e, v_e, wl_k, v_k);
        if (j > 0)
            t.source = "the \"" + std::string(eta) + "\" and \"" + k + "\" spectra";
        return t;
    }
    if (j > 0 && !props.has_property(mat))
        return std::nullopt;
    std::string material = props.get<std::string>(mat, MaterialName.def);
    auto resolve = [&](const std::string &name) {
        fs::path p = file_resolver()->resolve(name);
        if (!fs::exists(p))
            Throw("powder: cannot find \"%s\" (%s \"%s\"): import "
                  "mitsuba_powder, or add its folder to the file resolver "
                  "(mitsuba -a)", name, mat, material);
        return p.string();
    };
    if (const Material *m = find_material(material)) {
        powder::OpticalTable t = powder::load_refractiveindex_yaml(resolve(m->files[0]));
        if (m->files[1])
            t = powder::orientation_average(
                t, powder::load_refractiveindex_yaml(resolve(m->files[1])));
        t.source = m->source;
        return t;
    }
    if (string::ends_with(material, ".yml") || string::ends_with(material, ".yaml"))
        return powder::load_refractiveindex_yaml(resolve(material));
    std::string names;
    for (const Material &m : Materials)
        names += std::string("\"") + m.name + "\", ";
    Throw("powder: property \"%s\" = \"%s\" is not valid; valid values are "
          "%sor the path of a refractiveindex.info YAML file (.yml)", mat, material, names);
}

} // namespace powder_param

NAMESPACE_BEGIN(mitsuba)

/**
 * The traversal of a part of the BSDF's state by Dr.Jit (frozen functions): the JIT
 * variables of the members listed, as MI_TRAVERSE_CB gives the BSDF, which lists the part
 * among its own members. For the parts that are plain structs (no virtual methods).
 */
#define POWDER_TRAVERSE_MEMBERS(...)                                                      \
    void traverse_1_cb_ro(void *payload, drjit::detail::traverse_callback_ro fn) const {  \
        DRJIT_MARK_USED(payload);                                                         \
        DRJIT_MARK_USED(fn);                                                              \
        DRJIT_MAP(DR_TRAVERSE_MEMBER_RO, __VA_ARGS__)                                     \
    }                                                                                     \
    void traverse_1_cb_rw(void *payload, drjit::detail::traverse_callback_rw fn) {        \
        DRJIT_MARK_USED(payload);                                                         \
        DRJIT_MARK_USED(fn);                                                              \
        DRJIT_MAP(DR_TRAVERSE_MEMBER_RW, __VA_ARGS__)                                     \
    }

/**
 * The properties of a powder (read and checked by the constructor) and what follows from
 * them alone: which parameters are in use, their values at an interaction (a float or a
 * texture), and the evaluation wavelengths. A member of the BSDF (powder.cpp).
 */
template <typename Float, typename Spectrum> struct PowderParams {
    MI_IMPORT_TYPES(Texture)
    enum class SpecularModel : uint32_t { HarveyShack = 0, Gaussian = 1 };
    using Textures = PowderTextures<Float, Spectrum>;
    using Lobes = powder_param::Lobes;

    // ---------------------------------------------------------- properties

    /// Read and check the properties (the tables of powder_registry.h); warns when the
    /// extinction is outside the regime of the coherent term (warn_outside_regime)
    explicit PowderParams(const Properties &props) {
        using namespace powder_param;
        tau_given = props.has_property("tau_o");
        two_populations = props.has_property("radius2") || props.has_property("fraction2");
        populations = 1;
        for (size_t j = 1; j < MaxPopulations; ++j)
            if (props.has_property(Table[PopulationRadius[j]].name))
                populations = j + 1;
        std::tie(grain_model, mixing) = read_grain_model(props);
        // The float parameters; a fittable one may be a texture (evaluated at si.uv)
        for (size_t i = 0; i < Count; ++i) {
            const Spec &spec = Table[i];
            double value = spec.def;
            if (props.has_property(spec.name)) {
                auto type = props.type(spec.name);
                if (spec.fittable && (type == Properties::Type::Object ||
                                      type == Properties::Type::Reference ||
                                      type == Properties::Type::ResolvedReference)) {
                    textures[i] = props.get_texture<Texture>(spec.name);
                    Textures::check((Id) i, textures[i].get());
                } else {
                    value = props.get<double>(spec.name);
                    check_range(spec.name, value, spec.range);
                }
            }
            (*this)[(Id) i] = Float((ScalarFloat) value);
        }
        specular = (SpecularModel) read_choice<2>(props, "specular", SpecularValues);
        surface_fresnel = read_choice<2>(props, "surface_fresnel", SurfaceFresnelValues) == 1;
        if (surface_fresnel && tau_given && !props.has_property("eta") &&
            !props.has_property("material"))
            Throw("powder: property \"surface_fresnel\" = \"fresnel\" needs the grain "
                  "material's index, which \"tau_o\" given alone does not fix: give \"eta\" "
                  "and \"k\" (or \"material\") too, or surface_fresnel = \"none\"");
        lobes = parse_lobes(props.get<std::string>("lobes", LobeList.def));
        cosine_only = read_choice<2>(props, "sampling", SamplingValues) == 1;
        conserving = read_choice<2>(props, "energy", EnergyValues) == 1;
        if (conserving)
            for (size_t i = 0; i < Count; ++i)
                if (is_normalisation_param((Id) i) && textured((Id) i))
                    Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                          "uniform \"%s\" (the normalisation is tabulated per wavelength and "
                          "incidence), but it is a texture; use energy = \"paper\" or a "
                          "float", Table[i].name);
        double wavelength_nm = props.get<double>("wavelength", WavelengthNumber.def);
        check_range(WavelengthNumber.name, wavelength_nm, WavelengthNumber.range);
        wavelength = (ScalarFloat) wavelength_nm;
        std::array<double, 3> rgb = read_rgb_wavelengths(props);
        for (size_t i = 0; i < 3; ++i)
            rgb_wavelengths[i] = (ScalarFloat) rgb[i];
        optics = *load_optics(props);
        // the distinct materials of the populations (material_of: each one's)
        materials = { optics };
        for (size_t j = 1; j < populations; ++j) {
            std::optional<powder::OpticalTable> t = load_optics(props, j);
            material_of[j] = 0;
            if (!t)
                continue;
            size_t i = 0;
            while (i < materials.size() && materials[i].source != t->source)
                ++i;
            if (i == materials.size())
                materials.push_back(std::move(*t));
            material_of[j] = i;
        }
        if (!albedo_given(props))
            check_fraction_sum();
        if (materials.size() > 1 && !tau_given)
            for (size_t j = 1; j < populations; ++j)
                if (textured(PopulationFraction[j]))
                    Throw("powder: property \"%s\" is a texture, and the grain populations are "
                          "of different materials, so tau_o (from the mixture's Bruggeman "
                          "index) would vary over the surface: give \"tau_o\", or \"%s\" as a "
                          "float (docs/model.md, \"The mixture's index for tau_o\")",
                          Table[PopulationFraction[j]].name, Table[PopulationFraction[j]].name);
        if (props.has_property("albedo")) {
            albedo = props.get_texture<Texture>("albedo");
            Textures::check_albedo(albedo.get());
            if (conserving && albedo->is_spatially_varying())
                Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                      "uniform albedo (the normalisation is tabulated per wavelength and "
                      "incidence), but property \"albedo\" is a spatially varying texture; "
                      "use energy = \"paper\" or a uniform albedo");
        }
        warn_outside_regime();
    }

    static bool albedo_given(const Properties &props) { return props.has_property("albedo"); }

    /// The largest value a fraction holds (its texture's largest value)
    double largest(powder_param::Id p) const {
        if (textured(p))
            return texture_values(p).found ? texture_values(p).hi : 0.0;
        return std::get<1>(powder_param::lane_range((*this)[p]));
    }

    /// The fractions of populations 2..n sum to at most 1 (population 1 has the rest)
    void check_fraction_sum() const {
        if (populations < 2)
            return;
        double sum = 0.0;
        std::string names, values;
        for (size_t j = 1; j < populations; ++j) {
            powder_param::Id f = powder_param::PopulationFraction[j];
            sum += largest(f);
            names += std::string(j > 1 ? " + " : "") + powder_param::Table[f].name;
            values += std::string(j > 1 ? " + " : "") + std::to_string(largest(f));
        }
        if (!(sum <= 1.0 + 1e-6))
            Throw("powder: properties %s = %s = %g exceed 1; valid range of their sum is "
                  "[0, 1] (volume fractions of the solid; population 1 gets 1 - their sum)",
                  names, values, sum);
    }

    /// Check every parameter in use (a value per lane: each lane), as after an edit
    void check() const {
        if (!albedo)
            check_fraction_sum();
        for (size_t i = 0; i < powder_param::Count; ++i) {
            powder_param::Id p = (powder_param::Id) i;
            if (!in_use(p))
                continue;
            if (textures[i]) {
                Textures::check(p, textures[i].get());
                continue;
            }
            const Float &v = (*this)[p];
            powder_param::check_lanes(p, v);
            // the grain tables are built from one value (one per lane would be ignored),
            // and so is the normalisation of energy = "conserving"
            if (dr::width(v) > 1 && conserving && powder_param::is_normalisation_param(p))
                Throw("powder: property \"%s\" holds %zu values (one per lane); with energy "
                      "= \"conserving\" it takes one value (the normalisation is tabulated "
                      "for one); use energy = \"paper\" for one value per lane",
                      powder_param::Table[i].name, dr::width(v));
            if (dr::width(v) > 1 && powder_param::is_grain_param(p))
                Throw("powder: property \"%s\" holds %zu values (one per lane); a grain "
                      "property takes one value, or a texture for one per surface point",
                      powder_param::Table[i].name, dr::width(v));
        }
    }

    /// Largest kappa / k0 inside the regime of enhanced back-scattering theory
    /// (narrow coherent cone), above which the constructor warns
    static constexpr double RegimeLimit = 0.25;

    /// Warn when kappa / k0 = kappa lambda / (2 pi) exceeds RegimeLimit at a wavelength
    /// the powder is evaluated at (k0 is smallest at the longest one): the rgb_wavelengths,
    /// `wavelength` (mono) or the spectral table's range
    void warn_outside_regime() const {
        double lam_nm;
        if constexpr (is_spectral_v<Spectrum>)
            lam_nm = powder_param::TableMin +
                     (powder_param::TableSize - 1) * powder_param::TableStep;
        else if constexpr (is_rgb_v<Spectrum>)
            lam_nm = std::max({ (double) rgb_wavelengths[0], (double) rgb_wavelengths[1],
                                (double) rgb_wavelengths[2] });
        else
            lam_nm = wavelength;
        double k = textured(powder_param::Extinction)
                       ? texture_values(powder_param::Extinction).hi : value_of(kappa),
               ratio = k * lam_nm * 1e-3 / (2.0 * M_PI);
        if (ratio > RegimeLimit)
            Log(Warn,
                "powder: property \"extinction\" = %g 1/um (its largest value) gives "
                "kappa/k0 = %.4g at %g nm, "
                "above the threshold 0.25: outside the narrow-cone regime of enhanced "
                "back-scattering theory (kappa/k0 << 1), where the coherent term is not "
                "physical (with energy=\"paper\" a white powder reflects more than it "
                "receives; see docs/powder.md, \"Energy\")",
                k, ratio, lam_nm);
    }

    /// The value of a parameter that holds one value (lane 0 of a JIT array)
    template <typename T> static double value_of(const T &v) { return (double) dr::slice(v); }

    /// The member holding a float parameter of the table powder_param::Table
    static Float PowderParams::*member(powder_param::Id p) {
        static constexpr Float PowderParams::*members[powder_param::Count] = {
            &PowderParams::av, &PowderParams::g, &PowderParams::kappa, &PowderParams::tau_o,
            &PowderParams::thickness, &PowderParams::as, &PowderParams::lc, &PowderParams::sigma,
            &PowderParams::radius, &PowderParams::radius2, &PowderParams::fraction2,
            &PowderParams::agglomerate_radius, &PowderParams::agglomerate_fill,
            &PowderParams::radius3, &PowderParams::fraction3, &PowderParams::radius4,
            &PowderParams::fraction4
        };
        return members[p];
    }

    /// A float parameter of the table powder_param::Table (its float value)
    Float &operator[](powder_param::Id p) { return this->*member(p); }
    const Float &operator[](powder_param::Id p) const { return this->*member(p); }

    /// Whether a parameter enters the model as configured (range-checked, traversed)
    bool in_use(powder_param::Id p) const {
        switch (p) {
            case powder_param::TauO: return tau_given;
            case powder_param::Radius: return !albedo && !agglomerate();
            case powder_param::Radius2:
            case powder_param::Fraction2: return !albedo && populations >= 2;
            case powder_param::Radius3:
            case powder_param::Fraction3: return !albedo && populations >= 3;
            case powder_param::Radius4:
            case powder_param::Fraction4: return !albedo && populations >= 4;
            case powder_param::AgglomerateRadius:
            case powder_param::AgglomerateFill: return !albedo && agglomerate();
            case powder_param::CorrelationLength:
                return specular == SpecularModel::HarveyShack;
            case powder_param::Sigma: return specular == SpecularModel::Gaussian;
            default: return true;
        }
    }

    bool agglomerate() const { return grain_model == powder::GrainModel::Agglomerate; }

    /// Whether a float parameter is given as a texture
    bool textured(powder_param::Id p) const { return (bool) textures[p]; }

    /// A float parameter at an interaction: its texture at si.uv, or its value
    Float at(powder_param::Id p, const SurfaceInteraction3f &si, Mask active) const {
        if (textures[p])
            return textures[p]->eval_1(si, active);
        DRJIT_MARK_USED(si);
        DRJIT_MARK_USED(active);
        return (*this)[p];
    }

    TextureValues<Float, Spectrum> texture_values(powder_param::Id p) const {
        return TextureValues<Float, Spectrum>::of(textures[p].get());
    }

    // ------------------------------------------------------- wavelengths

    /// Evaluation wavelengths in micrometres, one per channel
    UnpolarizedSpectrum wavelengths_um(const SurfaceInteraction3f &si) const {
        if constexpr (is_spectral_v<Spectrum>) {
            return si.wavelengths * 1e-3f;
        } else if constexpr (is_rgb_v<Spectrum>) {
            return UnpolarizedSpectrum(rgb_wavelengths[0] * 1e-3f,
                                       rgb_wavelengths[1] * 1e-3f,
                                       rgb_wavelengths[2] * 1e-3f);
        } else {
            DRJIT_MARK_USED(si);
            return UnpolarizedSpectrum(wavelength * 1e-3f);
        }
    }

    /// 1 / wavelength in 1/micrometre, one per channel (1e3 / lambda_nm: one division
    /// per channel in spectral variants, constants otherwise)
    UnpolarizedSpectrum inverse_wavelengths_um(const SurfaceInteraction3f &si) const {
        if constexpr (is_spectral_v<Spectrum>)
            return 1e3f / si.wavelengths;
        else
            return dr::rcp(wavelengths_um(si));
    }

    /// Mean evaluation wavelength in micrometres (sets the sampling lobe widths)
    Float mean_wavelength(const SurfaceInteraction3f &si) const {
        if constexpr (is_spectral_v<Spectrum>) {
            return dr::mean(si.wavelengths) * 1e-3f;
        } else if constexpr (is_rgb_v<Spectrum>) {
            DRJIT_MARK_USED(si);
            return (rgb_wavelengths[0] + rgb_wavelengths[1] + rgb_wavelengths[2]) *
                   (1e-3f / 3.f);
        } else {
            DRJIT_MARK_USED(si);
            return wavelength * 1e-3f;
        }
    }

    // ------------------------------------------------------------- grains

    /// Whether a grain property that sets the albedo is a texture
    bool grain_textured() const {
        if (albedo)
            return false;
        if (agglomerate())
            return textured(powder_param::AgglomerateRadius) ||
                   textured(powder_param::AgglomerateFill);
        for (size_t j = 0; j < populations; ++j)
            if (textured(powder_param::PopulationRadius[j]) ||
                (j > 0 && textured(powder_param::PopulationFraction[j])))
                return true;
        return false;
    }

    /// The fraction of each population 2..n (population 1's entry unused)
    std::array<double, powder_param::MaxPopulations> fractions() const {
        std::array<double, powder_param::MaxPopulations> f{ 1.0, 0.0, 0.0, 0.0 };
        for (size_t j = 1; j < populations; ++j)
            f[j] = value_of((*this)[powder_param::PopulationFraction[j]]);
        return f;
    }

    /// The grain parameter the texture table runs over (its texture sets the lanes): the
    /// first population's size (powder_registry.h), or the fill of agglomerates
    powder_param::Id table_param() const {
        if (agglomerate() && textured(powder_param::AgglomerateFill))
            return powder_param::AgglomerateFill;
        return powder_param::GrainRules[(size_t) grain_model].size;
    }

    /// Smallest and largest value of a grain parameter (a radius in um, or the fill)
    std::pair<double, double> value_range(powder_param::Id p) const {
        if (textured(p)) {
            TextureValues<Float, Spectrum> v = texture_values(p);
            if (!v.found)
                Throw("powder: the texture of property \"%s\" exposes no values, so the "
                      "values to tabulate are unknown; use a bitmap or a constant texture",
                      powder_param::Table[p].name);
            return { v.lo, v.hi };
        }
        double r = value_of((*this)[p]);
        return { r, r };
    }

    /// An `albedo` that is one number for every wavelength and surface point (a
    /// `uniform` spectrum; in spectral variants the others depend on the wavelength)
    bool uniform_spectrum_albedo() const {
        return albedo && !albedo->is_spatially_varying() &&
               albedo->class_name() == "UniformSpectrum";
    }

    // ------------------------------------------------------------- values

    ref<Texture> albedo;                          ///< null: albedo from the grains
    /// the float parameters (powder_param::Table; member)
    Float av, g, kappa, tau_o, thickness, as, lc, sigma;
    Float radius, radius2, fraction2, agglomerate_radius, agglomerate_fill;
    Float radius3, fraction3, radius4, fraction4;
    ref<Texture> textures[powder_param::Count]; ///< texture-valued float parameters
    powder::GrainModel grain_model = powder::GrainModel::Sphere;
    powder::Mixing mixing = powder::Mixing::Bruggeman;
    bool tau_given = false, two_populations = false;
    size_t populations = 1;       ///< grain populations (1..4)
    SpecularModel specular;
    bool surface_fresnel = false, cosine_only = false;
    bool conserving = false;      ///< energy = "conserving"
    Lobes lobes;
    ScalarFloat wavelength;       ///< nm (mono)
    ScalarFloat rgb_wavelengths[3]; ///< nm (RGB)
    powder::OpticalTable optics; ///< the grain material's index (population 1)
    /// the distinct materials of the populations (the first is `optics`) and each
    /// population's among them
    std::vector<powder::OpticalTable> materials;
    std::array<size_t, powder_param::MaxPopulations> material_of{ 0, 0, 0, 0 };

    POWDER_TRAVERSE_MEMBERS(albedo, textures, av, g, kappa, tau_o, thickness, as, lc, sigma,
                            radius, radius2, fraction2, agglomerate_radius, agglomerate_fill,
                            radius3, fraction3, radius4, fraction4)
};

NAMESPACE_END(mitsuba)
