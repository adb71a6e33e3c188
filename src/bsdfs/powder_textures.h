#pragma once

/*
 * Texture-valued properties of the `powder` plugin: the values a texture holds (to check
 * them against a parameter's range at load and after edits) and the checks of a given
 * albedo.
 */

#include <mitsuba/core/properties.h>
#include <mitsuba/render/texture.h>

#include <drjit/tensor.h>

#include <exception>
#include <limits>
#include <vector>

#include "powder_registry.h"

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
    static void check_albedo(const Texture *albedo) {
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
            min_value = least_value(albedo);
        } catch (const std::exception &) {
            return; // this texture type cannot be evaluated in this variant
        }
        if (!(min_value >= 0.f))
            Throw("powder: property \"albedo\" has a minimum of %g; a "
                  "single-scattering albedo must lie in [0, 1]", (double) min_value);
    }

    /// Smallest value of a spatially uniform texture (over the 1 nm grid of the spectral
    /// tables in spectral variants, powder_registry.h), detached
    static ScalarFloat least_value(const Texture *texture) {
        constexpr int table_size = powder_param::TableSize;
        constexpr float table_min = powder_param::TableMin;
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

    /// The values of a spatially uniform texture at the wavelengths of the grain tables: the
    /// channels (RGB, mono), or the 1 nm grid of the spectral tables (powder_registry.h),
    /// detached; of a texture holding one value per lane (set through mi.traverse) the
    /// largest
    static std::vector<ScalarFloat> grid_values(const Texture *texture) {
        constexpr int table_size = powder_param::TableSize;
        constexpr float table_min = powder_param::TableMin, table_max = table_min + (table_size - 1);
        constexpr size_t C = dr::size_v<UnpolarizedSpectrum>;
        // lane i holds the wavelengths 4 i + c of the grid (spectral) in its channels c
        uint32_t lanes = is_spectral_v<Spectrum> ? (uint32_t) (table_size + 3) / 4 : 1;
        std::vector<ScalarFloat> result(lanes * C);
        if constexpr (dr::is_jit_v<Float>) { // every lane in one evaluation
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(lanes);
            if constexpr (is_spectral_v<Spectrum>) {
                UInt32 i = dr::arange<UInt32>(lanes);
                for (uint32_t c = 0; c < C; ++c)
                    si.wavelengths[c] = dr::minimum(table_min + Float(4u * i + c), table_max);
            }
            UnpolarizedSpectrum v = dr::detach(texture->eval(si));
            std::vector<ScalarFloat> channel(lanes);
            for (size_t c = 0; c < C; ++c) {
                Float x = v[c];
                if (dr::width(x) != lanes) // one value for all lanes, or one per lane
                    x = dr::max(x) + dr::zeros<Float>(lanes);
                dr::store(channel.data(), x);
                for (uint32_t i = 0; i < lanes; ++i)
                    result[i * C + c] = channel[i];
            }
        } else {
            for (uint32_t i = 0; i < lanes; ++i) {
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
                if constexpr (is_spectral_v<Spectrum>)
                    for (uint32_t c = 0; c < C; ++c)
                        si.wavelengths[c] = std::min(table_min + (float) (4 * i + c), table_max);
                UnpolarizedSpectrum v = texture->eval(si);
                for (size_t c = 0; c < C; ++c)
                    result[i * C + c] = v[c];
            }
        }
        if (is_spectral_v<Spectrum>)
            result.resize(table_size); // the last lane repeats the last node
        return result;
    }
};

NAMESPACE_END(mitsuba)
