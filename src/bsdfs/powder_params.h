#pragma once

/*
 * Reading and checking the properties of the `powder` plugin (the tables of
 * powder_registry.h): ranges, choices, the grain model's rules, the optical constants,
 * the lobes and wavelengths, and the values texture-valued parameters hold.
 */

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/string.h>
#include <mitsuba/render/texture.h>

#include <drjit/tensor.h>

#include <exception>
#include <limits>
#include <string>
#include <tuple>
#include <vector>

#include "powder_optics.h"
#include "powder_registry.h"

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
    bool any() const { return single || multiple || coherent || surface; }
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
        if (!(v > 0.0) || !std::isfinite(v))
            Throw("powder: property \"rgb_wavelengths\" = \"%s\": wavelength %g is "
                  "out of range; valid range is (0, inf) nm", spec, v);
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

/// (wavelengths in nm, values) of a float or spectrum property; a uniform
/// value gets a wavelength list spanning everything
inline std::pair<std::vector<double>, std::vector<double>>
read_spectrum(const Properties &props, const char *name) {
    auto type = props.type(name);
    if (type == Properties::Type::Float) {
        double v = props.get<double>(name);
        return { { 1.0, 1e6 }, { v, v } };
    }
    if (type == Properties::Type::Spectrum) {
        Properties::Spectrum spec = props.get<Properties::Spectrum>(name);
        if (spec.is_uniform())
            return { { 1.0, 1e6 }, { spec.values[0], spec.values[0] } };
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

/// Optical constants from `eta`/`k` or `material` (a built-in name or a YAML file)
inline powder::OpticalTable load_optics(const Properties &props) {
    bool has_eta = props.has_property("eta"), has_k = props.has_property("k");
    if (has_eta || has_k) {
        if (!(has_eta && has_k))
            Throw("powder: give both \"eta\" and \"k\" (got only \"%s\")", has_eta ? "eta" : "k");
        if (props.has_property("material"))
            Throw("powder: give either \"material\" or \"eta\" and \"k\", not both");
        auto [wl_e, v_e] = read_spectrum(props, "eta");
        auto [wl_k, v_k] = read_spectrum(props, "k");
        for (double v : v_e)
            check_range(EtaNumber.name, v, EtaNumber.range);
        for (double v : v_k)
            check_range(KNumber.name, v, KNumber.range);
        return powder::table_from_pairs(wl_e, v_e, wl_k, v_k);
    }
    std::string material = props.get<std::string>("material", MaterialName.def);
    auto resolve = [&](const std::string &name) {
        fs::path p = file_resolver()->resolve(name);
        if (!fs::exists(p))
            Throw("powder: cannot find \"%s\" (material \"%s\"): import "
                  "mitsuba_powder, or add its folder to the file resolver "
                  "(mitsuba -a)", name, material);
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
    Throw("powder: property \"material\" = \"%s\" is not valid; valid values are "
          "%sor the path of a refractiveindex.info YAML file (.yml)", material, names);
}

} // namespace powder_param

NAMESPACE_BEGIN(mitsuba)

/**
 * The smallest and largest values a texture holds: every floating-point
 * parameter it and the objects it holds expose through traverse() (a bitmap's
 * texels, the values of constant and checkerboard textures). `found` is false
 * when it exposes none (e.g. mesh attributes), `nan` when a value is NaN. Used
 * to check the range of texture-valued parameters at load and after edits.
 */
template <typename Float, typename Spectrum>
class TextureValues final : public TraversalCallback {
public:
    MI_IMPORT_CORE_TYPES()
    using UnpolarizedSpectrum = unpolarized_spectrum_t<Spectrum>;

    double lo = std::numeric_limits<double>::infinity(),
           hi = -std::numeric_limits<double>::infinity();
    bool found = false, nan = false;

    /// The values of a texture (traverse() only reads here; Mitsuba declares it non-const)
    template <typename Texture> static TextureValues of(const Texture *texture) {
        TextureValues values;
        const_cast<Texture *>(texture)->traverse(&values);
        return values;
    }

protected:
    void put_value(std::string_view, void *ptr, uint32_t,
                   const std::type_info &type) override {
        if (type == typeid(TensorXf)) {
            add(((TensorXf *) ptr)->array());
        } else if (type == typeid(Float)) {
            add(*(Float *) ptr);
        } else if (type == typeid(Color3f)) {
            for (size_t c = 0; c < 3; ++c)
                add((*(Color3f *) ptr)[c]);
        } else if constexpr (!std::is_same_v<UnpolarizedSpectrum, Color3f>) {
            if (type == typeid(UnpolarizedSpectrum))
                for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                    add((*(UnpolarizedSpectrum *) ptr)[c]);
        }
    }

    void put_object(std::string_view, Object *obj, uint32_t) override {
        if (obj)
            obj->traverse(this);
    }

private:
    template <typename T> void add(const T &v) {
        if constexpr (dr::is_jit_v<T>) {
            if (dr::width(v) == 0)
                return;
            found = true;
            T d = dr::detach(v);
            nan |= (bool) dr::slice(dr::any(dr::isnan(d)), 0);
            lo = std::min(lo, (double) dr::slice(dr::min(d), 0));
            hi = std::max(hi, (double) dr::slice(dr::max(d), 0));
        } else if constexpr (dr::is_dynamic_array_v<T>) {
            for (size_t i = 0; i < v.size(); ++i)
                add_one((double) v[i]);
        } else {
            add_one((double) v);
        }
    }

    void add_one(double x) {
        found = true;
        nan |= std::isnan(x);
        lo = std::min(lo, x);
        hi = std::max(hi, x);
    }
};

/// Checks of texture-valued properties
template <typename Float, typename Spectrum> struct PowderTextures {
    MI_IMPORT_TYPES(Texture)
    using Values = TextureValues<Float, Spectrum>;

    /**
     * Check every value a parameter's texture holds against the parameter's range
     * (a thickness texture must be finite); a texture that exposes no values is
     * accepted with a warning
     */
    static void check(powder_param::Id p, const Texture *texture) {
        const powder_param::Spec &spec = powder_param::Table[p];
        Values values = Values::of(texture);
        if (!values.found) {
            Log(Warn, "powder: the texture of property \"%s\" exposes no values, so its "
                      "range %s cannot be checked", spec.name, spec.range.str());
            return;
        }
        powder_param::Range range = spec.range;
        if (p == powder_param::Thickness)
            range.hi_closed = false; // finite: an infinite layer is a float
        if (values.nan || !range.contains(values.lo) || !range.contains(values.hi))
            Throw("powder: property \"%s\" is a texture with values from %g to %g%s; valid "
                  "range is %s", spec.name, values.lo, values.hi,
                  values.nan ? " and NaN" : "", range.str());
    }

    /// A single-scattering albedo must lie in [0, 1] (the minimum is checked where the
    /// texture is uniform and can be evaluated in this variant)
    static void check_albedo(const Texture *albedo, int table_size, float table_min) {
        ScalarFloat max_value;
        try {
            max_value = albedo->max();
        } catch (const std::exception &) {
            max_value = 1.f; // this texture type cannot report its maximum
        }
        if (!(max_value <= 1.f + 1e-5f))
            Throw("powder: property \"albedo\" has a maximum of %g; a "
                  "single-scattering albedo must lie in [0, 1]", (double) max_value);
        if (albedo->is_spatially_varying())
            return;
        ScalarFloat min_value;
        try {
            min_value = minimum(albedo, table_size, table_min);
        } catch (const std::exception &) {
            return; // this texture type cannot be evaluated in this variant
        }
        if (!(min_value >= 0.f))
            Throw("powder: property \"albedo\" has a minimum of %g; a "
                  "single-scattering albedo must lie in [0, 1]", (double) min_value);
    }

    /// Smallest value of a spatially uniform texture (over the 1 nm grid of table_size
    /// wavelengths from table_min in spectral variants), detached
    static ScalarFloat minimum(const Texture *texture, int table_size, float table_min) {
        ScalarFloat result = std::numeric_limits<ScalarFloat>::infinity();
        int steps = is_spectral_v<Spectrum> ? (table_size + 3) / 4 : 1;
        for (int i = 0; i < steps; ++i) {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(1);
            if constexpr (is_spectral_v<Spectrum>)
                for (size_t j = 0; j < 4; ++j)
                    si.wavelengths[j] = dr::minimum(table_min + (4 * i + j),
                                                    table_min + (table_size - 1));
            UnpolarizedSpectrum v = dr::detach(texture->eval(si));
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
                if constexpr (dr::is_jit_v<Float>)
                    result = std::min(result, (ScalarFloat) dr::slice(v[j], 0));
                else
                    result = std::min(result, (ScalarFloat) v[j]);
            }
        }
        return result;
    }
};

NAMESPACE_END(mitsuba)
