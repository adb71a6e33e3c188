#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>
#include <mitsuba/core/string.h>
#include <mitsuba/core/frame.h>
#include <mitsuba/core/warp.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/texture.h>

#include <drjit/tensor.h>
#include <nanothread/nanothread.h>

#include <array>
#include <tuple>

#include "powder_fresnel.h"
#include "powder_lobes.h"
#include "powder_optics.h"

#include <cmath>
#include <exception>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

NAMESPACE_BEGIN(mitsuba)

namespace powder_param {

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
};

/// Throw the project's error for a value outside its range
inline void check_range(const char *name, double value, const Range &r) {
    if (!r.contains(value))
        Throw("powder: property \"%s\" = %g is out of range; valid range is %s%g, %g%s", name,
              value, r.lo_closed ? "[" : "(", r.lo, r.hi, r.hi_closed ? "]" : ")");
}

constexpr double Inf = std::numeric_limits<double>::infinity();

/// Index of a string property's value among its `choices` (the first is the default);
/// throws the project's error naming the property, the value and the valid values
template <size_t N>
size_t read_choice(const Properties &props, const char *name,
                   const std::array<const char *, N> &choices) {
    std::string value = props.get<std::string>(name, choices[0]);
    for (size_t i = 0; i < N; ++i)
        if (value == choices[i])
            return i;
    std::string valid;
    for (size_t i = 0; i < N; ++i)
        valid += std::string(i ? (i + 1 == N ? " and " : ", ") : "") + "\"" + choices[i] + "\"";
    Throw("powder: property \"%s\" = \"%s\" is not valid; valid values are %s", name, value,
          valid);
}

/**
 * The float parameters of the model (docs/model.md, "Parameters"). One row each drives
 * reading the property (default, range), the range check after an edit through
 * mi.traverse (parameters_changed), the traversal key and whether it is
 * differentiable; tests/test_params_doc.py checks that the doc comment above the
 * class and docs/powder.md list the same names, defaults and ranges.
 */
struct Spec {
    const char *name;
    const char *unit;     ///< "-" when dimensionless
    double def;           ///< default value when the property is absent
    const char *def_doc;  ///< the default as documented
    Range range;
    bool fittable;        ///< differentiable and exposed by mi.traverse
};

enum Id : size_t {
    AmplitudeVolume, G, Extinction, TauO, Thickness, AmplitudeSurface, CorrelationLength,
    Sigma, Radius, Radius2, Fraction2, AgglomerateRadius, AgglomerateFill, Count
};

inline constexpr Spec Table[Count] = {
    // name                 unit    default  default as documented
    //     range {lo, hi, lo closed, hi closed}, fittable
    { "amplitude_volume",   "-",    1.0,     "1.0",
          { 0.0, Inf, true, false }, true },
    { "g",                  "-",    0.0,     "0.0",
          { -1.0, 1.0, false, false }, true },
    { "extinction",         "1/um", 1.0,     "1.0",
          { 0.0, Inf, false, false }, true },
    { "tau_o",              "-",    2.0 / 3, "from Fresnel of Re(eta)",
          { 0.0, Inf, true, false }, true },
    { "thickness",          "um",   Inf,     "infinite",
          { 0.0, Inf, true, true }, true },
    { "amplitude_surface",  "um^2", 0.0,     "0.0",
          { 0.0, Inf, true, false }, true },
    { "correlation_length", "um",   1.0,     "1.0",
          { 0.0, Inf, false, false }, true },
    { "sigma",              "rad",  0.1,     "0.1",
          { 0.0, 0.5 * M_PI, false, true }, true },
    { "radius",             "um",   0.017,   "0.017",
          { 0.0, Inf, false, false }, true },
    { "radius2",            "um",   1.0,     "none (one population)",
          { 0.0, Inf, false, false }, true },
    { "fraction2",          "-",    0.0,     "none (one population)",
          { 0.0, 1.0, true, true }, true },
    { "agglomerate_radius", "um",   1.0,     "none (required with agglomerates)",
          { 0.0, Inf, false, false }, true },
    { "agglomerate_fill",   "-",    0.5,     "0.5",
          { 0.0, 1.0, false, true }, true },
};


/// Whether a parameter describes the grains (it sets the Mie / grain tables)
inline bool is_grain_param(Id p) {
    return p == Radius || p == Radius2 || p == Fraction2 || p == AgglomerateRadius ||
           p == AgglomerateFill;
}

/// The parameters the normalisation of energy = "conserving" is tabulated from (one value
/// each: no texture, no value per lane)
inline bool is_normalisation_param(Id p) {
    return p == AmplitudeVolume || p == G || p == Extinction || p == TauO || p == Thickness ||
           is_grain_param(p);
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

} // namespace powder_param

/// Runs row(i) for i in [0, n) on Dr.Jit's thread pool (the grain tables' rows);
/// below 32 rows (RGB and mono tables) on the calling thread: too few to share
struct DrJitParallelFor {
    template <typename Row> void operator()(size_t n, Row &&row) const {
        if (n < 32) {
            for (size_t i = 0; i < n; ++i)
                row(i);
            return;
        }
        dr::parallel_for(dr::blocked_range<size_t>(0, n, 4),
                         [&](const dr::blocked_range<size_t> &range) {
                             for (size_t i = range.begin(); i != range.end(); ++i)
                                 row(i);
                         });
    }
};

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

/**!

.. _bsdf-powder:

Dry powder (:monosp:`powder`)
-----------------------------

.. pluginparameters::

 * - albedo
   - |spectrum| or |texture|
   - Single-scattering albedo rho of the grains, values in [0, 1] (Default: none:
     from Mie theory for the grains, see ``radius``)
   - |exposed|, |differentiable|

 * - grains
   - |string|
   - What scatters, without ``albedo`` (docs/model.md, "Grain models"): ``sphere`` (Default:
     isolated Mie spheres of radius ``radius``), ``agglomerate`` (Mie spheres of radius
     ``agglomerate_radius`` packed with crystallites of radius ``radius``; effective index
     by ``mixing``) or ``slab`` (Hapke's equivalent slab for grains of size 2 ``radius``
     much larger than the wavelength; needs Re(eta) > 1)

 * - radius
   - |float| or |texture|
   - Grain radius r in micrometres, without ``albedo``; the crystallite radius with
     agglomerates, where it only sets the size-parameter warning (Default: 0.017, range
     (0, inf); size parameter 2 pi r / lambda in [1e-3, 200] for spheres)
   - |exposed|, |differentiable| (not with agglomerates)

 * - radius2
   - |float| or |texture|
   - Radius of a second grain population in micrometres; needs ``fraction2``
     (Default: none (one population), range (0, inf))
   - |exposed|, |differentiable|

 * - fraction2
   - |float| or |texture|
   - Volume fraction of the second population; needs ``radius2``
     (Default: none (one population), range [0, 1])
   - |exposed|, |differentiable|

 * - agglomerate_radius
   - |float| or |texture|
   - Radius R_a of an agglomerate in micrometres; required with ``grains`` =
     ``agglomerate``, not allowed otherwise (Default: none (required with agglomerates),
     range (0, inf); size parameter 2 pi R_a / lambda in [1e-3, 200])
   - |exposed|, |differentiable|

 * - agglomerate_fill
   - |float| or |texture|
   - Volume fill f of crystallites in an agglomerate, ``grains`` = ``agglomerate`` only
     (Default: 0.5, range (0, 1])
   - |exposed|, |differentiable|

 * - mixing
   - |string|
   - Effective-medium rule of an agglomerate: ``bruggeman`` (Default) or
     ``maxwell_garnett``

 * - material
   - |string|
   - Grain material for Mie theory and tau_o: ``hematite``, ``magnetite`` or a
     refractiveindex.info YAML file (Default: ``hematite``)

 * - eta, k
   - |float| or |spectrum|
   - Optical constants n and k of the grain material, instead of ``material``; both or
     neither (Default: from ``material``, range eta > 0, k >= 0)

 * - amplitude_volume
   - |float| or |texture|
   - Amplitude A_v of the volume terms (Default: 1.0, range [0, inf))
   - |exposed|, |differentiable|

 * - g
   - |float| or |texture|
   - Henyey-Greenstein anisotropy of a grain (Default: 0.0, range (-1, 1))
   - |exposed|, |differentiable|

 * - extinction
   - |float| or |texture|
   - Extinction coefficient kappa in 1/micrometre (Default: 1.0, range (0, inf))
   - |exposed|, |differentiable|

 * - tau_o
   - |float| or |texture|
   - Extrapolation ratio of the diffusion boundary; exposed only when given
     (Default: from Fresnel of Re(eta), range [0, inf))
   - |exposed|, |differentiable|

 * - thickness
   - |float| or |texture|
   - Layer thickness d in micrometres (Default: infinite, range [0, inf])
   - |exposed|, |differentiable|

 * - amplitude_surface
   - |float| or |texture|
   - Surface amplitude A_s' in micrometre^2 (Harvey-Shack) or A_s (Gaussian)
     (Default: 0.0, range [0, inf))
   - |exposed|, |differentiable|

 * - correlation_length
   - |float| or |texture|
   - Correlation length l_c of the surface in micrometres, Harvey-Shack only
     (Default: 1.0, range (0, inf))
   - |exposed|, |differentiable|

 * - specular
   - |string|
   - Surface model: ``harvey_shack`` (Default) or ``gaussian``

 * - surface_fresnel
   - |string|
   - Reflectance factor of the surface term: ``none`` (Default: Eq. 23 as published) or
     ``fresnel``: both surface models times F(c) / F(1), the unpolarised Fresnel
     reflectance of the grain material (``material``, or ``eta`` and ``k``) at the half
     vector's cosine c, normalised to normal incidence (docs/model.md). With ``tau_o``
     given, needs ``eta`` and ``k`` or ``material``.

 * - sigma
   - |float| or |texture|
   - Half width of the Gaussian surface lobe in radians, Gaussian only (Default: 0.1,
     range (0, pi/2])
   - |exposed|, |differentiable|

 * - lobes
   - |string|
   - Comma-separated subset of ``single, multiple, coherent, surface``, or ``all``
     (Default: ``all``). Terms not listed are never evaluated.

 * - sampling
   - |string|
   - Importance sampling: ``lobes`` (Default: a mixture of the cosine lobe, the
     coherent cone and the surface lobe) or ``cosine`` (cosine-weighted only; for
     measuring what the lobes gain, see docs/benchmarks.md)

 * - energy
   - |string|
   - ``paper`` (Default: Eq. 23 as published) or ``conserving``: the volume terms are
     scaled per wavelength and incidence so that their hemispherical reflectance equals
     that of the ladder terms (L1 + L2) alone, at most 1: the coherent term redistributes
     flux instead of creating it (docs/powder.md, "Energy"). Needs a spatially uniform
     albedo.

 * - wavelength
   - |float|
   - Wavelength in nm at which mono variants evaluate the model (Default: 700,
     range (0, inf))

 * - rgb_wavelengths
   - |string|
   - Wavelengths in nm of the R, G, B channels in RGB variants
     (Default: ``611.3, 549.1, 464.3``)

The float parameters and their defaults and ranges are those of the table
``powder_param::Table`` above (tests/test_params_doc.py compares the two). Those
marked |texture| may be any Mitsuba texture of one channel (e.g. a ``bitmap`` with
``raw=true``), evaluated at ``si.uv``: every value it holds is checked against the
range at load and after ``mi.traverse`` edits (its ``<name>.data``), and a
thickness texture must be finite. A texture parameter is differentiable like
Mitsuba's own; constant parameters keep their precomputed fast paths.

The dry-powder reflectance model of Gerardin, Martinetto and Holzschuch
(JOSA A 40(9), 2023), Eq. 23, with the conventions and corrections of the
project's docs/model.md:

    f = A_v (L1 + L2 + C) / (4 pi) + S

where L1 is single scattering (Henyey-Greenstein), L2 the diffuse multiple
scattering ladder term, C the coherent back-scattering (cyclical) term and S
the Harvey-Shack (or Gaussian) surface term. The material is one-sided.

.. tabs::

    .. code-tab:: xml

        <bsdf type="powder">
            <rgb name="albedo" value="0.9, 0.5, 0.3"/>
            <float name="extinction" value="2.0"/>
            <float name="amplitude_surface" value="1e-4"/>
        </bsdf>

    .. code-tab:: python

        'type': 'powder',
        'albedo': {'type': 'rgb', 'value': [0.9, 0.5, 0.3]},
        'extinction': 2.0,
        'amplitude_surface': 1e-4,
*/
template <typename Float, typename Spectrum>
class Powder final : public BSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)

    enum class SpecularModel : uint32_t { HarveyShack = 0, Gaussian = 1 };
    using FloatStorage = DynamicBuffer<Float>;
    static constexpr int TableSize = 471;          ///< spectral grid: 360..830 nm
    static constexpr float TableMin = 360.f, TableStep = 1.f;

    Powder(const Properties &props) : Base(props) {
        m_tau_given = props.has_property("tau_o");
        m_two_populations = props.has_property("radius2") || props.has_property("fraction2");
        read_grain_model(props); // (first: agglomerates reject radius2 and fraction2)
        if (m_two_populations &&
            !(props.has_property("radius2") && props.has_property("fraction2")))
            Throw("powder: a second grain population needs both \"radius2\" and "
                  "\"fraction2\"; got only \"%s\"",
                  props.has_property("radius2") ? "radius2" : "fraction2");
        // The float parameters, from the table powder_param::Table; a fittable one may
        // be a texture (evaluated per interaction at si.uv)
        for (size_t i = 0; i < powder_param::Count; ++i) {
            const powder_param::Spec &spec = powder_param::Table[i];
            double value = spec.def;
            if (props.has_property(spec.name)) {
                auto type = props.type(spec.name);
                if (spec.fittable && (type == Properties::Type::Object ||
                                      type == Properties::Type::Reference ||
                                      type == Properties::Type::ResolvedReference)) {
                    m_textures[i] = props.get_texture<Texture>(spec.name);
                    check_texture((powder_param::Id) i);
                } else {
                    value = props.get<double>(spec.name);
                    powder_param::check_range(spec.name, value, spec.range);
                }
            }
            this->*member((powder_param::Id) i) = Float((ScalarFloat) value);
        }

        m_specular = powder_param::read_choice<2>(props, "specular",
                                                  { "harvey_shack", "gaussian" }) == 0
                         ? SpecularModel::HarveyShack : SpecularModel::Gaussian;
        m_surface_fresnel = powder_param::read_choice<2>(props, "surface_fresnel",
                                                         { "none", "fresnel" }) == 1;
        if (m_surface_fresnel && m_tau_given && !props.has_property("eta") &&
            !props.has_property("material"))
            Throw("powder: property \"surface_fresnel\" = \"fresnel\" needs the grain "
                  "material's index, which \"tau_o\" given alone does not fix: give \"eta\" "
                  "and \"k\" (or \"material\") too, or surface_fresnel = \"none\"");

        parse_lobes(props.get<std::string>("lobes", "all"));

        m_cosine_only = powder_param::read_choice<2>(props, "sampling",
                                                     { "lobes", "cosine" }) == 1;
        m_conserving = powder_param::read_choice<2>(props, "energy",
                                                    { "paper", "conserving" }) == 1;
        if (m_conserving)
            for (size_t i = 0; i < powder_param::Count; ++i)
                if (powder_param::Id p = (powder_param::Id) i;
                    powder_param::is_normalisation_param(p) && textured(p))
                    Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                          "uniform \"%s\" (the normalisation is tabulated per wavelength and "
                          "incidence), but it is a texture; use energy = \"paper\" or a "
                          "float", powder_param::Table[p].name);

        double wavelength = props.get<double>("wavelength", 700.0);
        powder_param::check_range("wavelength", wavelength,
                                  { 0.0, powder_param::Inf, false, false });
        m_wavelength = (ScalarFloat) wavelength;
        if (props.has_property("rgb_wavelengths") &&
            props.type("rgb_wavelengths") == Properties::Type::Vector) {
            // Python list / XML <vector>
            ScalarVector3d v = props.get<ScalarVector3d>("rgb_wavelengths");
            std::ostringstream oss;
            oss << v[0] << ", " << v[1] << ", " << v[2];
            parse_rgb_wavelengths(oss.str());
        } else {
            parse_rgb_wavelengths(
                props.get<std::string>("rgb_wavelengths", "611.3, 549.1, 464.3"));
        }

        // Grains: optical constants of the material
        m_optics = load_optics(props);

        if (props.has_property("albedo")) {
            m_albedo = props.get_texture<Texture>("albedo");
            check_albedo();
            if (m_conserving && m_albedo->is_spatially_varying())
                Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                      "uniform albedo (the normalisation is tabulated per wavelength and "
                      "incidence), but property \"albedo\" is a spatially varying texture; "
                      "use energy = \"paper\" or a uniform albedo");
        }

        warn_outside_regime();

        // Wavelengths (nm) of the grain tables: a 1 nm grid for spectral
        // variants, the evaluation wavelengths otherwise
        if constexpr (is_spectral_v<Spectrum>) {
            for (int i = 0; i < TableSize; ++i)
                m_table_wavelengths.push_back(TableMin + i * TableStep);
        } else if constexpr (is_rgb_v<Spectrum>) {
            m_table_wavelengths.assign(m_rgb_wavelengths, m_rgb_wavelengths + 3);
        } else {
            m_table_wavelengths.push_back(m_wavelength);
        }
        for (double wl : m_table_wavelengths)
            m_index.push_back(m_optics.eval(wl * 1e-3)); // throws if outside the table
        if (!m_albedo)
            warn_crystallite_size();

        if (!m_tau_given) {
            std::vector<ScalarFloat> tau;
            for (const auto &m : m_index)
                tau.push_back((ScalarFloat) powder::tau_o_fresnel(m.real()));
            m_tau_table = dr::load<FloatStorage>(tau.data(), tau.size());
            m_tau_table_constant =
                std::all_of(tau.begin(), tau.end(), [&](ScalarFloat t) { return t == tau[0]; });
        }

        if (m_surface_fresnel)
            set_fresnel_index();

        // Components: volume (diffuse), coherent back-scattering and surface (glossy)
        if (m_single || m_multiple) {
            m_comp_volume = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide);
        }
        if (m_coherent) {
            m_comp_coherent = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::GlossyReflection | BSDFFlags::FrontSide);
        }
        if (m_surface) {
            m_comp_surface = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::GlossyReflection | BSDFFlags::FrontSide);
        }
        m_flags = 0;
        for (uint32_t c : m_components)
            m_flags |= c;

        parameters_changed();
    }

    void traverse(TraversalCallback *cb) override {
        for (size_t i = 0; i < powder_param::Count; ++i) {
            if (!exposed((powder_param::Id) i))
                continue;
            // (the agglomerate property a grain texture table holds at one value is not)
            bool held = agglomerate() && !m_albedo && grain_textured() &&
                        (i == powder_param::AgglomerateRadius ||
                         i == powder_param::AgglomerateFill) &&
                        i != (size_t) table_param();
            uint32_t flags = (uint32_t) (powder_param::Table[i].fittable && !held
                                             ? ParamFlags::Differentiable
                                             : ParamFlags::NonDifferentiable);
            if (m_textures[i]) // e.g. "g.data" for a bitmap, as Mitsuba's own textures
                cb->put(powder_param::Table[i].name, m_textures[i], flags);
            else
                cb->put(powder_param::Table[i].name, this->*member((powder_param::Id) i), flags);
        }
        if (m_albedo)
            cb->put("albedo", m_albedo, ParamFlags::Differentiable);
    }

    void parameters_changed(const std::vector<std::string> &keys = {}) override {
        // Parameters edited through mi.traverse() are checked like properties
        for (size_t i = 0; i < powder_param::Count; ++i) {
            if (!in_use((powder_param::Id) i))
                continue;
            if (m_textures[i]) {
                check_texture((powder_param::Id) i);
                continue;
            }
            const Float &v = this->*member((powder_param::Id) i);
            powder_param::check_lanes((powder_param::Id) i, v);
            // the grain tables are built from one value (one per lane would be ignored),
            // and so is the normalisation of energy = "conserving"
            bool normalised =
                m_conserving && powder_param::is_normalisation_param((powder_param::Id) i);
            if (dr::width(v) > 1 && normalised)
                Throw("powder: property \"%s\" holds %zu values (one per lane); with energy "
                      "= \"conserving\" it takes one value (the normalisation is tabulated "
                      "for one); use energy = \"paper\" for one value per lane",
                      powder_param::Table[i].name, dr::width(v));
            if (dr::width(v) > 1 && powder_param::is_grain_param((powder_param::Id) i))
                Throw("powder: property \"%s\" holds %zu values (one per lane); a grain "
                      "property takes one value, or a texture for one per surface point",
                      powder_param::Table[i].name, dr::width(v));
        }

        // An infinite layer needs no thickness factor (and 0 * inf would
        // poison the gradients of the extinction); a thickness texture is finite.
        // With one thickness per lane, the factor is evaluated when any is finite (it
        // is 1 in the infinite lanes)
        m_finite_thickness = textured(powder_param::Thickness) ||
                             std::isfinite(std::get<0>(powder_param::lane_range(m_thickness)));

        // Opaque first: the Mie tangents below must not bake the radius in as a literal
        // (that would compile a new kernel for every radius an optimiser tries)
        for (size_t i = 0; i < powder_param::Count; ++i)
            dr::make_opaque(this->*member((powder_param::Id) i));

        bool grains_changed = keys.empty();
        for (powder_param::Id p : { powder_param::Radius, powder_param::Radius2,
                                    powder_param::Fraction2, powder_param::AgglomerateRadius,
                                    powder_param::AgglomerateFill })
            grains_changed |= string::contains(keys, powder_param::Table[p].name);
        if (!m_albedo && grain_textured())
            update_grain_texture_table();
        else if (!m_albedo && grains_changed)
            update_mie_tables();
        if (m_albedo && (keys.empty() || string::contains(keys, "albedo")))
            check_albedo();

        if constexpr (is_spectral_v<Spectrum>)
            pack_grain_tables();

        // RGB and mono: the grain tables hold one value per channel; keep them as
        // opaque scalars, so that eval reads a broadcast value instead of gathering
        if constexpr (!is_spectral_v<Spectrum>) {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                if (!m_albedo)
                    m_rho_channels[c] = dr::gather<Float>(m_rho_table, UInt32((uint32_t) c));
                if (!m_tau_given)
                    m_tau_channels[c] = dr::gather<Float>(m_tau_table, UInt32((uint32_t) c));
            }
            dr::make_opaque(m_rho_channels, m_tau_channels);
        }

        if (!is_spectral_v<Spectrum> && !textured(powder_param::Extinction)) {
            m_k0_kappa = dr::TwoPi<ScalarFloat> /
                         (wavelengths_um(dr::zeros<SurfaceInteraction3f>(1)) * m_kappa);
            dr::make_opaque(m_k0_kappa);
        }

        // The volume constants are the same for every interaction when the albedo
        // and tau_o are: precompute them (opaque, so no recompilation per value)
        // (spectral: when the albedo is one number for every wavelength and so is tau_o:
        // given, or from a constant index)
        m_uniform_volume = (!m_albedo || !m_albedo->is_spatially_varying()) &&
                           !textured(powder_param::G) && !textured(powder_param::TauO) &&
                           !grain_textured();
        m_thick_volume = false;
        if constexpr (is_spectral_v<Spectrum>) {
            m_uniform_volume &= uniform_spectrum_albedo();
            if (m_uniform_volume && !m_tau_given && !m_tau_table_constant)
                m_uniform_volume = m_thick_volume = optically_thick();
        }
        if (m_uniform_volume) {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(1);
            // optically thick (see optically_thick): s(c0) = 1 / (2 c0), and tau_o, which
            // neither L2 nor C then reads, is set to its smallest value (x0 below)
            m_volume = volume_constants(albedo(si, true),
                                        m_thick_volume ? UnpolarizedSpectrum(dr::min(m_tau_table))
                                                       : tau_o(si, true),
                                        m_g);
            if (m_thick_volume)
                m_volume.s_c0 = .5f / m_volume.c0;
            dr::make_opaque(m_volume.rho, m_volume.rho2_3, m_volume.c0_sq, m_volume.c0,
                            m_volume.s_c0, m_volume.tau);
        }

        // Spectral: the same constants per wavelength, tabulated on the 1 nm grid
        m_tabulated_volume = false;
        if constexpr (is_spectral_v<Spectrum>)
            if (!m_uniform_volume)
                update_volume_table();
        if (!m_tabulated_volume)
            m_volume_table = FloatStorage(); // no stale table (nor its AD graph) kept

        // In C, x = 2 c tau_o >= 2 c0 tau_o =: x0 (c0 and tau_o of every lane and
        // channel, or of every node of the wavelength table, between which eval
        // interpolates). Where x0 >= 18, 1 - exp(-x) rounds to 1 in single precision
        // for every direction (exp(-18) < 2^-25): eval skips the exponential; where
        // x0 >= 0.03, the series branch of (1 - exp(-x)) / x is never taken: eval skips
        // it. Same values either way.
        double x0 = 0.0;
        if (m_uniform_volume) {
            x0 = powder_param::Inf;
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                x0 = std::min(x0, std::get<0>(powder_param::lane_range(
                                      2.f * dr::detach(m_volume.c0[c]) *
                                      dr::detach(m_volume.tau[c]))));
        } else if (m_tabulated_volume) {
            x0 = m_volume_table_x0;
        }
        // (x0 in double from single-precision values; eval's x in single precision can be
        // a few ulp below it: the margin keeps both decisions on the safe side)
        x0 *= 1.0 - SaturationMargin;
        m_coherent_saturated = m_thick_volume || (m_tabulated_volume && m_volume_table_thick) ||
                               x0 >= CoherentSaturation;
        m_coherent_series = !(x0 >= CoherentSeriesLimit);

        // Detached means, used only to weight the sampling lobes
        m_rho_mean = m_albedo ? dr::detach(m_albedo->mean())
                              : grain_textured() ? Float((ScalarFloat) m_grain_rho_mean)
                              : Float(dr::mean(dr::detach(m_rho_table)));
        m_tau_mean = !m_tau_given ? Float(dr::mean(m_tau_table))
                     : textured(powder_param::TauO)
                         ? Float(dr::detach(m_textures[powder_param::TauO]->mean()))
                         : dr::detach(m_tau_o);

        dr::make_opaque(m_rho_mean, m_tau_mean);

        if (m_conserving)
            update_energy_norm();
    }

    // -----------------------------------------------------------------------
    //  BSDF interface
    // -----------------------------------------------------------------------

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx,
                                             const SurfaceInteraction3f &si,
                                             Float sample1,
                                             const Point2f &sample2,
                                             Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFSample, active);

        Lobes lobes = enabled_lobes(ctx);
        BSDFSample3f bs = dr::zeros<BSDFSample3f>();
        Float mu_i = Frame3f::cos_theta(si.wi);
        active &= mu_i > 0.f;

        if (unlikely(!lobes.any() || dr::none_or<false>(active)))
            return { bs, 0.f };

        Float lam_mean = mean_wavelength(si);
        LobeWeights w = lobe_weights(si, lam_mean, lobes);

        Mask pick_coherent = active && (sample1 < w.coherent),
             pick_surface  = active && !pick_coherent &&
                             (sample1 < w.coherent + w.surface),
             pick_diffuse  = active && !pick_coherent && !pick_surface;

        // sample1 picks the lobe, sample2 draws the direction from it
        Vector3f wo = warp::square_to_cosine_hemisphere(sample2);
        if (lobes.coherent)
            dr::masked(wo, pick_coherent) = sample_coherent(si.wi, w.width_coherent, sample2);
        if (lobes.surface)
            dr::masked(wo, pick_surface) = sample_surface(si.wi, w.width_surface, sample2);

        auto [value, pdf] = eval_pdf_impl(lobes, si, wo, w, active);

        bs.wo = wo;
        bs.pdf = pdf;
        bs.eta = 1.f;
        // The cosine lobe samples the volume terms; when they are not enabled it
        // is only a fallback of the glossy lobes, reported as the first of them
        bool volume = lobes.single || lobes.multiple;
        uint32_t cosine_type = volume ? +BSDFFlags::DiffuseReflection
                                      : +BSDFFlags::GlossyReflection,
                 cosine_component = volume ? m_comp_volume
                                   : lobes.coherent ? m_comp_coherent : m_comp_surface;
        bs.sampled_type = dr::select(pick_diffuse, UInt32(cosine_type),
                                     UInt32(+BSDFFlags::GlossyReflection));
        bs.sampled_component = dr::select(
            pick_diffuse, UInt32(cosine_component),
            dr::select(pick_coherent, UInt32(m_comp_coherent), UInt32(m_comp_surface)));

        Mask valid = active && pdf > 0.f;
        UnpolarizedSpectrum weight = dr::select(valid, value / dr::select(valid, pdf, 1.f), 0.f);
        return { bs, depolarizer<Spectrum>(weight) & valid };
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                  const Vector3f &wo, Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFEvaluate, active);
        Lobes lobes = enabled_lobes(ctx);
        if (unlikely(!lobes.any()))
            return 0.f;
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        UnpolarizedSpectrum value =
            eval_brdf(lobes, si, wo, wavelengths_um(si), active) * Frame3f::cos_theta(wo);
        return depolarizer<Spectrum>(dr::select(active, value, 0.f));
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
              const Vector3f &wo, Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFEvaluate, active);
        Lobes lobes = enabled_lobes(ctx);
        if (unlikely(!lobes.any()))
            return 0.f;
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        Float lam_mean = mean_wavelength(si);
        LobeWeights w = lobe_weights(si, lam_mean, lobes);
        return pdf_impl(lobes, si, wo, w, active);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx,
                                        const SurfaceInteraction3f &si,
                                        const Vector3f &wo,
                                        Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFEvaluate, active);
        Lobes lobes = enabled_lobes(ctx);
        if (unlikely(!lobes.any()))
            return { 0.f, 0.f };
        Float lam_mean = mean_wavelength(si);
        LobeWeights w = lobe_weights(si, lam_mean, lobes);
        auto [value, pdf] = eval_pdf_impl(lobes, si, wo, w, active);
        return { depolarizer<Spectrum>(value), pdf };
    }

    Spectrum eval_diffuse_reflectance(const SurfaceInteraction3f &si,
                                      Mask active) const override {
        return depolarizer<Spectrum>(albedo(si, active));
    }

    /// Attributes: "albedo" (rho), "tau_o", and with the Mie path "q_ext",
    /// "q_sca" (first population) and "q_ext2", "q_sca2" (second)
    Mask has_attribute(const std::string &name, Mask /*active*/) const override {
        bool tables = !m_albedo && !grain_textured();
        return name == "albedo" || name == "tau_o" ||
               (tables && (name == "q_ext" || name == "q_sca")) ||
               (tables && m_two_populations && (name == "q_ext2" || name == "q_sca2"));
    }

    UnpolarizedSpectrum eval_attribute(const std::string &name,
                                       const SurfaceInteraction3f &si,
                                       Mask active) const override {
        if (name == "albedo")
            return albedo(si, active);
        if (name == "tau_o")
            return tau_o(si, active);
        if (!dr::any_nested(has_attribute(name, active)))
            Throw("powder: no attribute \"%s\"; available: albedo, tau_o%s", name,
                  m_albedo || grain_textured()
                      ? "" : (m_two_populations ? ", q_ext, q_sca, q_ext2, q_sca2"
                                                : ", q_ext, q_sca"));
        const FloatStorage &table = name == "q_ext" ? m_qext_table
                                  : name == "q_sca" ? m_qsca_table
                                  : name == "q_ext2" ? m_qext2_table : m_qsca2_table;
        return lookup(table, si, active);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        auto show = [&](powder_param::Id p) {
            return m_textures[p] ? string::indent(m_textures[p])
                                 : string::indent(this->*member(p));
        };
        oss << "Powder[" << std::endl
            << "  amplitude_volume = " << show(powder_param::AmplitudeVolume) << ","
            << std::endl
            << "  g = " << show(powder_param::G) << "," << std::endl
            << "  extinction = " << show(powder_param::Extinction) << " [1/um]," << std::endl
            << "  albedo = " << (m_albedo ? string::indent(m_albedo)
                                          : std::string("from the grains")) << "," << std::endl;
        if (!m_albedo)
            oss << "  grains = "
                << (m_grain_model == powder::GrainModel::Sphere ? "sphere"
                    : agglomerate() ? "agglomerate" : "slab") << "," << std::endl;
        oss << "  radius = " << string::indent(m_radius) << " [um]," << std::endl;
        if (!m_albedo && agglomerate())
            oss << "  agglomerate_radius = " << string::indent(m_agglomerate_radius)
                << " [um]," << std::endl
                << "  agglomerate_fill = " << string::indent(m_agglomerate_fill) << ","
                << std::endl
                << "  mixing = "
                << (m_mixing == powder::Mixing::Bruggeman ? "bruggeman" : "maxwell_garnett")
                << "," << std::endl;
        if (m_two_populations)
            oss << "  radius2 = " << string::indent(m_radius2) << " [um]," << std::endl
                << "  fraction2 = " << string::indent(m_fraction2) << "," << std::endl;
        oss << "  optical constants = " << m_optics.source << "," << std::endl
            << "  tau_o = " << (m_tau_given ? show(powder_param::TauO)
                                            : std::string("from Fresnel (Re eta)"))
            << "," << std::endl
            << "  thickness = " << show(powder_param::Thickness) << " [um]," << std::endl
            << "  specular = " << (m_specular == SpecularModel::HarveyShack
                                       ? "harvey_shack" : "gaussian") << "," << std::endl
            << "  surface_fresnel = " << (m_surface_fresnel ? "fresnel" : "none") << ","
            << std::endl
            << "  amplitude_surface = " << show(powder_param::AmplitudeSurface) << ","
            << std::endl;
        if (m_specular == SpecularModel::HarveyShack)
            oss << "  correlation_length = " << show(powder_param::CorrelationLength)
                << " [um]," << std::endl;
        else
            oss << "  sigma = " << show(powder_param::Sigma) << " [rad]," << std::endl;
        oss << "  lobes = \"" << lobes_string() << "\"," << std::endl
            << "  sampling = " << (m_cosine_only ? "cosine" : "lobes") << "," << std::endl
            << "  energy = " << (m_conserving ? "conserving" : "paper") << "," << std::endl
            << "  volume constants = " << volume_path() << "," << std::endl
            << "  wavelength = " << m_wavelength << " [nm] (mono)," << std::endl
            << "  rgb_wavelengths = " << m_rgb_wavelengths[0] << ", "
            << m_rgb_wavelengths[1] << ", " << m_rgb_wavelengths[2] << " [nm] (rgb)" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(Powder)

private:
    /// Which terms a call evaluates: the `lobes` property and the BSDF context
    struct Lobes {
        bool single, multiple, coherent, surface;
        bool any() const { return single || multiple || coherent || surface; }
    };

    /// Probabilities of the coherent and surface sampling lobes (the cosine
    /// lobe gets the rest, at least 0.1) and their widths
    struct LobeWeights {
        Float coherent, surface;
        Float width_coherent; ///< scale of the projected 2D Cauchy lobe
        Float width_surface;  ///< std. dev. (projected plane or radians)
    };

    Lobes enabled_lobes(const BSDFContext &ctx) const {
        bool volume = ctx.is_enabled(BSDFFlags::DiffuseReflection, m_comp_volume);
        return { m_single && volume, m_multiple && volume,
                 m_coherent && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_coherent),
                 m_surface && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_surface) };
    }

    // ------------------------------------------------------- wavelengths

    /// Evaluation wavelengths in micrometres, one per channel
    UnpolarizedSpectrum wavelengths_um(const SurfaceInteraction3f &si) const {
        if constexpr (is_spectral_v<Spectrum>) {
            return si.wavelengths * 1e-3f;
        } else if constexpr (is_rgb_v<Spectrum>) {
            return UnpolarizedSpectrum(m_rgb_wavelengths[0] * 1e-3f,
                                       m_rgb_wavelengths[1] * 1e-3f,
                                       m_rgb_wavelengths[2] * 1e-3f);
        } else {
            DRJIT_MARK_USED(si);
            return UnpolarizedSpectrum(m_wavelength * 1e-3f);
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
            return (m_rgb_wavelengths[0] + m_rgb_wavelengths[1] + m_rgb_wavelengths[2]) *
                   (1e-3f / 3.f);
        } else {
            DRJIT_MARK_USED(si);
            return m_wavelength * 1e-3f;
        }
    }

    // ------------------------------------------------------------- grains

    /// Single-scattering albedo per channel: the `albedo` texture or the Mie table
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if (m_albedo)
            return m_albedo->eval(si, active);
        if (grain_textured())
            return grain_texture_albedo(si, active);
        if constexpr (is_spectral_v<Spectrum>)
            return lookup_grains(si, active).first;
        else
            return m_rho_channels;
    }

    /// Extrapolation ratio per channel: the `tau_o` property or the Fresnel table
    UnpolarizedSpectrum tau_o(const SurfaceInteraction3f &si, Mask active) const {
        if (m_tau_given)
            return UnpolarizedSpectrum(at(powder_param::TauO, si, active));
        if constexpr (is_spectral_v<Spectrum>)
            return lookup_grains(si, active).second;
        else
            return m_tau_channels;
    }

    /// surface_fresnel: F(c) / F(1) per channel for the grain index at the channel
    /// wavelengths (RGB, mono: per channel; spectral: interpolated on the 1 nm grid, as
    /// tau_o) and the cosine c at the half vector
    UnpolarizedSpectrum surface_fresnel_factor(const SurfaceInteraction3f &si, const Float &c,
                                               Mask active) const {
        if constexpr (is_spectral_v<Spectrum>) {
            if (m_fresnel_constant) // one index for every wavelength: no lookup
                return powder::fresnel_unpolarized(UnpolarizedSpectrum(c), m_fresnel_eta,
                                                   m_fresnel_k) * m_fresnel_inv_f1;
            UnpolarizedSpectrum t = table_position(si), out(0.f);
            for (size_t ch = 0; ch < dr::size_v<UnpolarizedSpectrum>; ++ch) {
                UInt32 i0 = UInt32(dr::floor(t[ch]));
                auto v = dr::gather<dr::Array<Float, 4>>(m_records.fresnel, i0, active);
                Float w = t[ch] - Float(i0), eta = dr::lerp(v[0], v[1], w),
                      k = dr::lerp(v[2], v[3], w);
                out[ch] = powder::fresnel_unpolarized(c, eta, k) /
                          powder::fresnel_normal(eta, k);
            }
            return out;
        } else {
            DRJIT_MARK_USED(si);
            DRJIT_MARK_USED(active);
            return powder::fresnel_unpolarized(UnpolarizedSpectrum(c), m_fresnel_eta,
                                               m_fresnel_k) * m_fresnel_inv_f1;
        }
    }

    /// surface_fresnel: the grain index n + i k at the table wavelengths (m_index), as
    /// per-channel constants (RGB, mono) or interpolation records (spectral). The factor
    /// is undefined where the interface reflects nothing at normal incidence (m = 1)
    void set_fresnel_index() {
        std::vector<ScalarFloat> eta, k;
        for (size_t i = 0; i < m_index.size(); ++i) {
            const std::complex<double> &m = m_index[i];
            // below 1e-5 (|m - 1| < 0.0063) F(1) is ill-conditioned in single precision
            if (double f1 = powder::fresnel_normal(m.real(), m.imag()); !(f1 >= 1e-5))
                Throw("powder: property \"surface_fresnel\" = \"fresnel\": the grain index "
                      "%g + %gi at %g nm is too close to 1: the smooth interface reflects "
                      "almost nothing (F(1) = %g < 1e-5), and the factor F(c) / F(1) is not "
                      "defined to single precision", m.real(), m.imag(),
                      m_table_wavelengths[i], f1);
            eta.push_back((ScalarFloat) m.real());
            k.push_back((ScalarFloat) m.imag());
        }
        m_fresnel_constant =
            std::all_of(eta.begin(), eta.end(), [&](ScalarFloat v) { return v == eta[0]; }) &&
            std::all_of(k.begin(), k.end(), [&](ScalarFloat v) { return v == k[0]; });
        if (is_spectral_v<Spectrum> && m_fresnel_constant) {
            m_fresnel_eta = eta[0];
            m_fresnel_k = k[0];
            m_fresnel_inv_f1 =
                (ScalarFloat) (1.0 / powder::fresnel_normal((double) eta[0], (double) k[0]));
        } else if constexpr (is_spectral_v<Spectrum>) {
            size_t n = eta.size();
            std::vector<ScalarFloat> packed(4 * n);
            for (size_t i = 0; i < n; ++i) {
                size_t j = std::min(i + 1, n - 1);
                packed[4 * i + 0] = eta[i];
                packed[4 * i + 1] = eta[j];
                packed[4 * i + 2] = k[i];
                packed[4 * i + 3] = k[j];
            }
            m_records.fresnel = dr::load<FloatStorage>(packed.data(), packed.size());
        } else {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                m_fresnel_eta[c] = eta[c];
                m_fresnel_k[c] = k[c];
                m_fresnel_inv_f1[c] =
                    (ScalarFloat) (1.0 / powder::fresnel_normal((double) eta[c], (double) k[c]));
            }
        }
    }

    /// Spectral variants: each channel's position in the 1 nm grain tables (entry
    /// floor(t), weight t - floor(t) of the next), clamped inside the table
    static UnpolarizedSpectrum table_position(const SurfaceInteraction3f &si) {
        return dr::clip((si.wavelengths - TableMin) * (1.f / TableStep), 0.f,
                        (float) (TableSize - 1) - 1e-3f);
    }

    /// Spectral variants: (rho, tau_o) per channel from m_packed, with the same
    /// linear interpolation on the 1 nm grid as lookup(), but one packet gather
    /// of 4 values per channel instead of 2 gathers per table (gathers dominate
    /// the cost of eval on CPUs with slow vector gathers)
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    lookup_grains(const SurfaceInteraction3f &si, Mask active) const {
        UnpolarizedSpectrum rho(0.f), tau(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            UnpolarizedSpectrum t = table_position(si);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                UInt32 i0 = UInt32(dr::floor(t[c]));
                auto v = dr::gather<dr::Array<Float, 4>>(m_packed, i0, active);
                Float w = t[c] - Float(i0);
                rho[c] = dr::lerp(v[0], v[1], w);
                tau[c] = dr::lerp(v[2], v[3], w);
            }
        } else {
            DRJIT_MARK_USED(si);
            DRJIT_MARK_USED(active);
        }
        return { rho, tau };
    }

    /// Spectral variants: pack rho and tau_o as records (rho[i], rho[i + 1],
    /// tau[i], tau[i + 1]) for lookup_grains (zeros for a table not in use);
    /// differentiable through the gathers from m_rho_table
    void pack_grain_tables() {
        uint32_t n = (uint32_t) TableSize;
        std::vector<uint32_t> src(4 * n), is_rho(4 * n);
        for (uint32_t i = 0; i < n; ++i)
            for (uint32_t j = 0; j < 4; ++j) {
                src[4 * i + j] = std::min(i + (j & 1u), n - 1);
                is_rho[4 * i + j] = j < 2;
            }
        if constexpr (dr::is_jit_v<Float>) {
            using UInt32Storage = DynamicBuffer<UInt32>;
            UInt32Storage idx = dr::load<UInt32Storage>(src.data(), src.size()),
                          sel = dr::load<UInt32Storage>(is_rho.data(), is_rho.size());
            FloatStorage rho = m_albedo ? dr::zeros<FloatStorage>(4 * n)
                                        : dr::gather<FloatStorage>(m_rho_table, idx),
                         tau = m_tau_given ? dr::zeros<FloatStorage>(4 * n)
                                           : dr::gather<FloatStorage>(m_tau_table, idx);
            m_packed = dr::select(sel != 0u, rho, tau);
            dr::make_opaque(m_packed);
        } else {
            std::vector<ScalarFloat> packed(4 * n);
            for (size_t k = 0; k < packed.size(); ++k) {
                const FloatStorage &table = is_rho[k] ? m_rho_table : m_tau_table;
                bool unused = is_rho[k] ? (bool) m_albedo : m_tau_given;
                packed[k] = unused ? 0.f : (ScalarFloat) table[src[k]];
            }
            m_packed = dr::load<FloatStorage>(packed.data(), packed.size());
        }
    }

    /// A grain table at the channel wavelengths: linear interpolation on the
    /// 1 nm grid (spectral), or one entry per channel (RGB, mono)
    UnpolarizedSpectrum lookup(const FloatStorage &table, const SurfaceInteraction3f &si,
                               Mask active) const {
        UnpolarizedSpectrum out(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            UnpolarizedSpectrum t = table_position(si);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                UInt32 i0 = UInt32(dr::floor(t[c]));
                Float w = t[c] - Float(i0);
                out[c] = dr::lerp(dr::gather<Float>(table, i0, active),
                                  dr::gather<Float>(table, i0 + 1u, active), w);
            }
        } else {
            DRJIT_MARK_USED(si);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                out[c] = dr::gather<Float>(table, UInt32((uint32_t) c), active);
        }
        return out;
    }

    /// The grain model (`grains`, `mixing`) and the properties each model requires or
    /// rejects (docs/model.md, "Grain models")
    void read_grain_model(const Properties &props) {
        static constexpr const char *Models[3] = { "sphere", "agglomerate", "slab" };
        size_t model = powder_param::read_choice<3>(props, "grains",
                                                    { Models[0], Models[1], Models[2] });
        m_grain_model = (powder::GrainModel) model;
        bool agglomerate = m_grain_model == powder::GrainModel::Agglomerate;
        if (props.has_property("albedo"))
            for (const char *name : { "grains", "agglomerate_radius", "agglomerate_fill",
                                      "mixing" })
                if (props.has_property(name))
                    Throw("powder: property \"%s\" has no effect together with \"albedo\" "
                          "(a given albedo replaces the one computed from the grains); give "
                          "one or the other", name);
        for (const char *name : { "agglomerate_radius", "agglomerate_fill", "mixing" })
            if (!agglomerate && props.has_property(name))
                Throw("powder: property \"%s\" is used only with grains = \"agglomerate\" "
                      "(here grains = \"%s\")", name, Models[model]);
        if (agglomerate && !props.has_property("agglomerate_radius"))
            Throw("powder: grains = \"agglomerate\" needs property \"agglomerate_radius\" "
                  "(radius of an agglomerate in micrometres; valid range is (0, inf))");
        if (agglomerate && m_two_populations)
            Throw("powder: property \"%s\" (a second grain population) cannot be used with "
                  "grains = \"agglomerate\", which has one population; valid with grains = "
                  "\"sphere\" or \"slab\"",
                  props.has_property("radius2") ? "radius2" : "fraction2");
        size_t mixing = powder_param::read_choice<2>(props, "mixing",
                                                     { "bruggeman", "maxwell_garnett" });
        m_mixing = (powder::Mixing) mixing;
    }

    /// Agglomerates: warn when the crystallites are too large for a mixing rule
    /// (size parameter 2 pi r |n + ik| / lambda above 0.5 at some table wavelength)
    void warn_crystallite_size() const {
        if (m_grain_model != powder::GrainModel::Agglomerate)
            return;
        std::vector<double> x = powder::crystallite_size_parameters(
            value_of(m_radius), m_table_wavelengths, m_index);
        size_t worst = 0, over = 0;
        double longest = 0.0; // longest wavelength (nm) above the limit
        for (size_t i = 0; i < x.size(); ++i) {
            if (x[i] > x[worst])
                worst = i;
            if (x[i] > CrystalliteLimit) {
                ++over;
                longest = std::max(longest, m_table_wavelengths[i]);
            }
        }
        if (over > 0)
            Log(Warn,
                "powder: crystallites of radius %g um have the size parameter 2 pi r |n + ik| "
                "/ lambda = %.3g at %g nm, above %g (the limit of an effective-medium mixing "
                "rule) at %zu of the %zu wavelengths evaluated, the longest %g nm; the "
                "agglomerate albedo is outside the model's validity there (docs/model.md, \"Grain "
                "models\")", value_of(m_radius), x[worst], m_table_wavelengths[worst],
                CrystalliteLimit, over, x.size(), longest);
    }

    /// Largest crystallite size parameter for which a mixing rule holds (docs/model.md)
    static constexpr double CrystalliteLimit = 0.5;

    /// Optical constants from `eta`/`k` or `material` (name or YAML file)
    static powder::OpticalTable load_optics(const Properties &props) {
        bool has_eta = props.has_property("eta"), has_k = props.has_property("k");
        if (has_eta || has_k) {
            if (!(has_eta && has_k))
                Throw("powder: give both \"eta\" and \"k\" (got only \"%s\")",
                      has_eta ? "eta" : "k");
            if (props.has_property("material"))
                Throw("powder: give either \"material\" or \"eta\" and \"k\", not both");
            auto [wl_e, v_e] = read_spectrum(props, "eta");
            auto [wl_k, v_k] = read_spectrum(props, "k");
            for (double v : v_e)
                powder_param::check_range("eta", v, { 0.0, powder_param::Inf, false, false });
            for (double v : v_k)
                powder_param::check_range("k", v, { 0.0, powder_param::Inf, true, false });
            return powder::table_from_pairs(wl_e, v_e, wl_k, v_k);
        }
        std::string material = props.get<std::string>("material", "hematite");
        auto resolve = [&](const std::string &name) {
            fs::path p = file_resolver()->resolve(name);
            if (!fs::exists(p))
                Throw("powder: cannot find \"%s\" (material \"%s\"): import "
                      "mitsuba_powder, or add its folder to the file resolver "
                      "(mitsuba -a)", name, material);
            return p.string();
        };
        if (material == "hematite") {
            powder::OpticalTable o = powder::load_refractiveindex_yaml(
                resolve("data/optical_constants/hematite_Querry-o.yml"));
            powder::OpticalTable e = powder::load_refractiveindex_yaml(
                resolve("data/optical_constants/hematite_Querry-e.yml"));
            return powder::orientation_average(o, e);
        }
        if (material == "magnetite") {
            powder::OpticalTable t = powder::load_refractiveindex_yaml(
                resolve("data/optical_constants/magnetite_Querry.yml"));
            t.source = "magnetite (Querry 1985)";
            return t;
        }
        if (string::ends_with(material, ".yml") || string::ends_with(material, ".yaml"))
            return powder::load_refractiveindex_yaml(resolve(material));
        Throw("powder: property \"material\" = \"%s\" is not valid; valid values are "
              "\"hematite\", \"magnetite\" or the path of a refractiveindex.info YAML "
              "file (.yml)", material);
    }

    /// (wavelengths in nm, values) of a float or spectrum property; a uniform
    /// value gets an empty wavelength list spanning everything
    static std::pair<std::vector<double>, std::vector<double>>
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

    /// Mie efficiencies, rho = Q_sca / Q_ext (two populations: docs/model.md), and,
    /// when gradients are tracked on a grain parameter, rho's first derivatives
    /// with respect to the radii and fraction, attached to the AD graph as tangents.
    /// The table (powder_optics.h) spreads the wavelengths over Dr.Jit's threads.
    void update_mie_tables() {
        powder::Grains grains{ value_of(m_radius), value_of(m_radius2),
                               value_of(m_fraction2), m_two_populations, m_grain_model,
                               value_of(m_agglomerate_radius), value_of(m_agglomerate_fill),
                               m_mixing };
        // the grain parameters in use, each with its column of derivatives
        std::vector<std::pair<Float *, double powder::AlbedoRow::*>> grain_params;
        for (auto [p, d] : { std::pair{ powder_param::Radius, &powder::AlbedoRow::d_r1 },
                             std::pair{ powder_param::Radius2, &powder::AlbedoRow::d_r2 },
                             std::pair{ powder_param::Fraction2, &powder::AlbedoRow::d_f2 },
                             std::pair{ powder_param::AgglomerateRadius,
                                        &powder::AlbedoRow::d_ra },
                             std::pair{ powder_param::AgglomerateFill,
                                        &powder::AlbedoRow::d_fill } })
            if (in_use(p))
                grain_params.emplace_back(&(this->*member(p)), d);
        bool tangents = false;
        if constexpr (dr::is_diff_v<Float>)
            for (auto &gp : grain_params)
                tangents |= dr::grad_enabled(*gp.first);
        std::vector<powder::AlbedoRow> rows = powder::albedo_table(
            grains, m_table_wavelengths, m_index, tangents, DrJitParallelFor());

        size_t n = rows.size();
        std::vector<ScalarFloat> rho(n), qe1(n), qs1(n), qe2(n), qs2(n);
        for (size_t i = 0; i < n; ++i) {
            const powder::AlbedoRow &r = rows[i];
            rho[i] = (ScalarFloat) r.rho;
            qe1[i] = (ScalarFloat) r.q_ext1;
            qs1[i] = (ScalarFloat) r.q_sca1;
            qe2[i] = (ScalarFloat) r.q_ext2;
            qs2[i] = (ScalarFloat) r.q_sca2;
        }

        auto load = [](const std::vector<ScalarFloat> &v) {
            return dr::load<FloatStorage>(v.data(), v.size());
        };
        m_rho_table = load(rho);
        if constexpr (dr::is_diff_v<Float>) {
            if (tangents) {
                // value unchanged (the differences are zero), first derivatives exact
                for (auto &[param, column] : grain_params) {
                    std::vector<ScalarFloat> d(n);
                    for (size_t i = 0; i < n; ++i)
                        d[i] = (ScalarFloat) (rows[i].*column);
                    m_rho_table = m_rho_table + load(d) * (*param - dr::detach(*param));
                }
            }
        }
        m_qext_table = load(qe1);
        m_qsca_table = load(qs1);
        if (m_two_populations) {
            m_qext2_table = load(qe2);
            m_qsca2_table = load(qs2);
        }
        dr::make_opaque(m_rho_table);
    }

    /// Spatially varying grains: relative accuracy of the tabulated albedo (checked at
    /// every interval's midpoint) and the largest table (wavelengths x nodes)
    static constexpr double GrainTableTolerance = 2e-4;
    static constexpr size_t GrainTableRecords = 200000;

    /// Whether a grain property that sets the albedo is a texture
    bool grain_textured() const {
        return !m_albedo &&
               (agglomerate() ? textured(powder_param::AgglomerateRadius) ||
                                    textured(powder_param::AgglomerateFill)
                              : textured(powder_param::Radius) ||
                                    (m_two_populations && (textured(powder_param::Radius2) ||
                                                           textured(powder_param::Fraction2))));
    }

    /// The grain parameter that is the (first) population's radius
    powder_param::Id radius_id() const {
        return agglomerate() ? powder_param::AgglomerateRadius : powder_param::Radius;
    }

    /// Whether the grain texture table runs over the fill of agglomerates (an
    /// agglomerate_fill texture) rather than over a radius
    bool fill_table() const {
        return agglomerate() && textured(powder_param::AgglomerateFill);
    }

    /// The grain parameter the texture table runs over (its texture sets the lanes)
    powder_param::Id table_param() const {
        return fill_table() ? powder_param::AgglomerateFill : radius_id();
    }

    /// Smallest and largest value of a grain parameter (a radius in um, or the fill),
    /// texture or float
    std::pair<double, double> radius_range(powder_param::Id p) const {
        if (textured(p)) {
            TextureValues<Float, Spectrum> v = texture_values(p);
            if (!v.found)
                Throw("powder: the texture of property \"%s\" exposes no values, so the "
                      "values to tabulate are unknown; use a bitmap or a constant texture",
                      powder_param::Table[p].name);
            return { v.lo, v.hi };
        }
        double r = value_of(this->*member(p));
        return { r, r };
    }

    /**
     * Spatially varying grains (a radius, radius2, fraction2 or agglomerate_radius
     * texture): tabulate Q_ext and Q_sca over ln r (powder::efficiency_table) for the
     * radii the textures hold, widened by a factor 1.25 each way so that edits of the
     * texture usually stay inside (outside, the table is rebuilt); with an
     * agglomerate_fill texture, over the fill (widened by 0.05 each way inside (0, 1])
     * at the float agglomerate_radius. The table is rebuilt when the agglomerate
     * property it holds at one value changes. eval interpolates per lane and mixes the
     * populations (grain_texture_albedo). Differentiable through the interpolation.
     */
    void update_grain_texture_table() {
        bool fill = fill_table();
        if (fill && textured(powder_param::AgglomerateRadius))
            Throw("powder: properties \"agglomerate_fill\" and \"agglomerate_radius\" "
                  "are both textures; the albedo table of spatially varying agglomerates "
                  "runs over one of them: give the other as a float");
        // the table holds the other agglomerate property at one value: its gradient
        // would be lost
        powder_param::Id held = fill ? powder_param::AgglomerateRadius
                                     : powder_param::AgglomerateFill;
        if constexpr (dr::is_diff_v<Float>)
            if (agglomerate() && dr::grad_enabled(this->*member(held)))
                Throw("powder: property \"%s\" is not differentiable while \"%s\" is a "
                      "texture (the albedo table runs over the texture's values at one "
                      "%s)", powder_param::Table[held].name,
                      powder_param::Table[table_param()].name,
                      powder_param::Table[held].name);
        double held_value = agglomerate() ? value_of(this->*member(held)) : 0.0;
        auto [lo, hi] = radius_range(table_param());
        if (m_two_populations && !agglomerate()) {
            auto [lo2, hi2] = radius_range(powder_param::Radius2);
            lo = std::min(lo, lo2);
            hi = std::max(hi, hi2);
        }
        if (m_grain_table.nodes > 0 && lo >= m_grain_table_lo && hi <= m_grain_table_hi &&
            held_value == m_grain_table_held)
            return; // the current table covers the values
        if (fill) {
            // fills in (0, 1]: widened by 0.05 each way where they can be (a single
            // fill of 1 gets the interval [0.95, 1])
            double lo_t = std::max(lo - 0.05, 0.5 * lo), hi_t = std::min(hi + 0.05, 1.0);
            powder::Grains grains{ 1.0, 1.0, 0.0, false, m_grain_model,
                                   value_of(m_agglomerate_radius), 0.5, m_mixing };
            build_grain_texture_table(grains, lo, hi, lo_t, hi_t, powder::TableAxis::Fill,
                                      held_value);
            return;
        }
        double lo_t = lo / 1.25, hi_t = hi * 1.25;
        if (m_grain_model != powder::GrainModel::Slab) {
            // keep the widened range inside the size parameters Mie accepts
            double wl_lo = *std::min_element(m_table_wavelengths.begin(),
                                             m_table_wavelengths.end()),
                   wl_hi = *std::max_element(m_table_wavelengths.begin(),
                                             m_table_wavelengths.end());
            lo_t = std::max(lo_t, std::min(lo, 1e-3 * wl_hi * 1e-3 / (2.0 * M_PI)));
            hi_t = std::min(hi_t, std::max(hi, 200.0 * wl_lo * 1e-3 / (2.0 * M_PI)));
        }
        hi_t = std::max(hi_t, lo_t * 1.001);
        powder::Grains grains{ 1.0, 1.0, 0.0, false, m_grain_model,
                               1.0, value_of(m_agglomerate_fill), m_mixing };
        build_grain_texture_table(grains, lo, hi, lo_t, hi_t, powder::TableAxis::LogRadius,
                                  held_value);
    }

    /// Build the grain texture table over [lo_t, hi_t] of its variable (covering the
    /// texture values [lo, hi]; `held`: the value of the agglomerate property the
    /// table holds) and upload its records
    void build_grain_texture_table(const powder::Grains &grains, double lo, double hi,
                                   double lo_t, double hi_t, powder::TableAxis axis,
                                   double held) {
        bool fill = axis == powder::TableAxis::Fill;
        double error = 0.0;
        m_grain_table = powder::efficiency_table(
            grains, lo_t, hi_t, m_table_wavelengths, m_index,
            powder_param::Table[table_param()].name, GrainTableTolerance, GrainTableRecords,
            error, DrJitParallelFor(), axis);
        if (error > GrainTableTolerance)
            Log(Warn, "powder: the albedo table of %s %g-%g%s is accurate to %.2g "
                      "(relative, at the midpoints of its %zu nodes), not %g: the values "
                      "span too many Mie resonances for %zu records; narrow the texture's "
                      "range", fill ? "fills" : "radii", lo_t, hi_t, fill ? "" : " um",
                error, m_grain_table.nodes, GrainTableTolerance, GrainTableRecords);
        m_grain_table_lo = lo_t;
        m_grain_table_hi = hi_t;
        m_grain_table_held = held;
        std::vector<ScalarFloat> rec(m_grain_table.records.begin(),
                                     m_grain_table.records.end());
        m_grain_records = dr::load<FloatStorage>(rec.data(), rec.size());
        dr::make_opaque(m_grain_records);
        m_grain_u0 = (ScalarFloat) m_grain_table.u0;
        m_grain_du = (ScalarFloat) m_grain_table.du;
        // a mean albedo for the sampling weights only: at the middle of the range
        double r_mid = fill ? 0.5 * (lo + hi) : std::sqrt(lo * hi), rho = 0.0;
        for (size_t i = 0; i < m_table_wavelengths.size(); ++i) {
            auto [qe, qs] = powder::efficiency_at(m_grain_table, i, r_mid);
            rho += qs / qe;
        }
        m_grain_rho_mean = rho / (double) m_table_wavelengths.size();
        // the constant-radius tables are not used; keep them valid for packing
        size_t n = m_table_wavelengths.size();
        m_rho_table = dr::zeros<FloatStorage>(n);
        m_qext_table = m_qsca_table = m_qext2_table = m_qsca2_table = dr::zeros<FloatStorage>(n);
    }

    /// (Q_ext, Q_sca) per channel of grains of radius r (um, per lane; or of the
    /// fill of agglomerates, fill_table()) from the efficiency table: cubic Hermite
    /// in ln r (in the fill), and in spectral variants linear in wavelength on the
    /// 1 nm grid, as the constant tables
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    grain_efficiencies(const Float &r, const SurfaceInteraction3f &si, Mask active) const {
        uint32_t nodes = (uint32_t) m_grain_table.nodes;
        Float u = m_grain_table.axis == powder::TableAxis::Fill ? r : dr::log(r);
        Float t = dr::clip((u - m_grain_u0) * (1.f / m_grain_du), 0.f,
                           (float) (nodes - 1) - 1e-3f);
        UInt32 j = UInt32(dr::floor(dr::detach(t)));
        Float s = t - Float(j), one_s = 1.f - s,
              h00 = (1.f + 2.f * s) * dr::square(one_s), h10 = s * dr::square(one_s) * m_grain_du,
              h01 = dr::square(s) * (3.f - 2.f * s), h11 = dr::square(s) * (s - 1.f) * m_grain_du;
        auto hermite = [&](const UInt32 &row) {
            auto v = dr::gather<dr::Array<Float, 8>>(m_grain_records, row * nodes + j, active);
            return std::pair<Float, Float>(h00 * v[0] + h10 * v[2] + h01 * v[4] + h11 * v[6],
                                           h00 * v[1] + h10 * v[3] + h01 * v[5] + h11 * v[7]);
        };
        UnpolarizedSpectrum qe, qs;
        if constexpr (is_spectral_v<Spectrum>) {
            UnpolarizedSpectrum pos = table_position(si);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                UInt32 i0 = UInt32(dr::floor(pos[c]));
                Float w = pos[c] - Float(i0);
                auto [e0, s0] = hermite(i0);
                auto [e1, s1] = hermite(i0 + 1u);
                qe[c] = dr::lerp(e0, e1, w);
                qs[c] = dr::lerp(s0, s1, w);
            }
        } else {
            DRJIT_MARK_USED(si);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                auto [e, q] = hermite(UInt32((uint32_t) c));
                qe[c] = e;
                qs[c] = q;
            }
        }
        return { qe, qs };
    }

    /// The albedo of spatially varying grains per lane: rho = sum_j (f_j / r_j)
    /// Q_sca,j / sum_j (f_j / r_j) Q_ext,j (docs/model.md; slab: Q_ext = 1, Q_sca = rho)
    UnpolarizedSpectrum grain_texture_albedo(const SurfaceInteraction3f &si,
                                             Mask active) const {
        Float r1 = at(table_param(), si, active);
        auto [qe1, qs1] = grain_efficiencies(r1, si, active);
        if (!m_two_populations)
            return qs1 / qe1;
        Float r2 = at(powder_param::Radius2, si, active),
              f2 = at(powder_param::Fraction2, si, active),
              w1 = (1.f - f2) / r1, w2 = f2 / r2;
        auto [qe2, qs2] = grain_efficiencies(r2, si, active);
        return (w1 * qs1 + w2 * qs2) / (w1 * qe1 + w2 * qe2);
    }

    // ---------------------------------------------------------- the model

    /// k0 / kappa = 2 pi / (lambda kappa) per channel (lambda in um), docs/model.md Eq. 10;
    /// precomputed in RGB and mono variants, where lambda is fixed, unless the
    /// extinction is a texture
    /// (inv_lam: 1 / lambda per channel, shared with the surface lobe: one division per
    /// channel instead of two)
    UnpolarizedSpectrum k0_over_kappa(const UnpolarizedSpectrum &inv_lam,
                                      const SurfaceInteraction3f &si, Mask active) const {
        if (is_spectral_v<Spectrum> || textured(powder_param::Extinction))
            return inv_lam * (dr::TwoPi<ScalarFloat> / at(powder_param::Extinction, si, active));
        return m_k0_kappa;
    }

    /// Per-channel values of the volume terms that depend on the grains only
    /// (rho, g, tau_o), not on the directions
    struct VolumeConstants {
        UnpolarizedSpectrum rho,
            rho2_3, ///< 3 rho^2, the prefactor of L2 and C
            c0_sq,  ///< c0^2 = 3 (1 - rho) (1 - rho g), docs/model.md Eq. 10e with alpha = 0
            c0,
            s_c0,   ///< s(c0), docs/model.md Eq. 9b
            tau;    ///< tau_o
        DRJIT_STRUCT(VolumeConstants, rho, rho2_3, c0_sq, c0, s_c0, tau)
    };

    VolumeConstants volume_constants(const UnpolarizedSpectrum &rho,
                                     const UnpolarizedSpectrum &tau, const Float &g) const {
        VolumeConstants k;
        k.rho = rho;
        k.tau = tau;
        k.rho2_3 = 3.f * dr::square(rho);
        k.c0_sq = dr::maximum(3.f * (1.f - rho) * (1.f - rho * g), 0.f);
        k.c0 = dr::sqrt(k.c0_sq);
        k.s_c0 = powder::s_func(k.c0, tau);
        return k;
    }

    /// The volume constants at an interaction: precomputed in parameters_changed
    /// when they are the same for every interaction (RGB and mono variants with
    /// a Mie albedo or a spatially uniform albedo texture)
    VolumeConstants volume_constants(const SurfaceInteraction3f &si, Mask active) const {
        if (m_uniform_volume)
            return m_volume;
        if constexpr (is_spectral_v<Spectrum>)
            if (m_tabulated_volume)
                return lookup_volume(si, active);
        Float g = at(powder_param::G, si, active);
        if constexpr (is_spectral_v<Spectrum>) {
            if (!m_albedo && !m_tau_given && !grain_textured()) { // one packet gather
                auto [rho, tau] = lookup_grains(si, active);
                return volume_constants(rho, tau, g);
            }
        }
        return volume_constants(albedo(si, active), tau_o(si, active), g);
    }

    /**
     * Spectral variants, an albedo that is one number and tau_o from the Fresnel table:
     * whether the layer is optically thick at every wavelength, x0 = 2 c0 tau_o >=
     * ThickLimit at every node of the table (c0 from the albedo and g, tau_o its smallest
     * entry). s(c) = (1 - exp(-2 c tau_o)) / (2 c) (docs/model.md Eq. 9b) depends on tau_o
     * only through exp(-2 c tau_o) <= exp(-x0) <= 2^-18 (3.8e-6) for every c >= c0: eval
     * takes s(c) = 1 / (2 c), so that neither L2 nor C depends on tau_o, the volume
     * constants are the same for every wavelength and are computed once per parameter
     * change, and eval reads no table and skips the exponential of C. L2 and C change by
     * at most 3.8e-6 relative (tests/test_fast_paths.py); their derivatives with respect
     * to the albedo and g by at most x0 exp(-x0). The same holds for an albedo from the
     * grain tables (table_thickness bounds x0 over every interval of the 1 nm grid): the
     * table then holds rho alone, and eval computes c0 and s(c0) = 1 / (2 c0) from it.
     */
    bool optically_thick() const {
        Float rho = m_albedo->eval(dr::zeros<SurfaceInteraction3f>(1), true)[0],
              c0 = dr::sqrt(dr::maximum(3.f * (1.f - rho) * (1.f - rho * m_g), 0.f));
        double x0 = std::get<0>(powder_param::lane_range(
            2.f * dr::detach(c0) * dr::min(dr::detach(m_tau_table))));
        return x0 * (1.0 - SaturationMargin) >= ThickLimit;
    }

    /// Smallest x0 = 2 c0 tau_o for which spectral variants treat the layer as optically
    /// thick (optically_thick): 18 ln 2, where exp(-x0) = 2^-18
    static constexpr double ThickLimit = 12.476649250079015;

    /// Smallest x = 2 c tau_o from which 1 - exp(-x) rounds to 1 in single precision
    /// (exp(-18) < 2^-25); C skips the exponential there
    static constexpr double CoherentSaturation = 18.0;

    /// Relative margin by which x0, computed in double from single-precision values, must
    /// clear CoherentSaturation and CoherentSeriesLimit (eval's x in single precision can
    /// be a few ulp below it)
    static constexpr double SaturationMargin = 1e-5;

    /// Smallest x = 2 c tau_o for which C takes (1 - exp(-x)) / x in closed form
    /// (below it, its series: powder::one_minus_exp_neg_over_x)
    static constexpr double CoherentSeriesLimit = 0.03;

    /// An `albedo` that is one number for every wavelength and surface point (a
    /// `uniform` spectrum; in spectral variants the others depend on the wavelength)
    bool uniform_spectrum_albedo() const {
        return m_albedo && !m_albedo->is_spatially_varying() &&
               m_albedo->class_name() == "UniformSpectrum";
    }

    /// How eval obtains the volume constants (to_string, tests)
    std::string volume_path() const {
        if (m_uniform_volume)
            return m_thick_volume ? "once per parameter change (optically thick)"
                                  : "once per parameter change";
        if (m_tabulated_volume)
            return m_volume_table_rho_given ? "1 nm table of s(c0), tau_o"
                   : m_volume_table_thick   ? "1 nm table of rho (optically thick)"
                                            : "1 nm table of rho, s(c0), tau_o";
        return "per lane";
    }

    /**
     * Spectral variants: when the volume constants depend on the wavelength only (the
     * albedo from the grain tables, or one number; tau_o from the Fresnel table or one
     * number; one g), tabulate them on the 1 nm grid as records of the two nodes
     * bracketing each interval: (rho, s(c0), tau_o) per node, or (s(c0), tau_o) when
     * the albedo is one number (rho and c0 in m_volume). lookup_volume reads them with
     * one packet gather per channel, and computes no s(c0) (an exponential, a division).
     * rho and tau_o are interpolated linearly in wavelength as before, and c0 computed
     * from rho as before; s(c0) is interpolated instead of recomputed (L2 differs by
     * 2.3e-5 relative for a Mie albedo of 100 nm grains, 7.7e-5 for a mix with 300 nm
     * grains, tests/test_fast_paths.py). Differentiable:
     * Dr.Jit arithmetic on the grain tables, g, tau_o and the albedo.
     */
    void update_volume_table() {
        m_volume_table_x0 = 0.0;
        m_volume_table_thick = false;
        if (grain_textured() || textured(powder_param::G) || textured(powder_param::TauO) ||
            dr::width(m_g) != 1 || (m_tau_given && dr::width(m_tau_o) != 1))
            return;
        if (m_albedo && !uniform_spectrum_albedo())
            return;
        const size_t n = (size_t) TableSize;
        SurfaceInteraction3f si0 = dr::zeros<SurfaceInteraction3f>(1);
        Float rho_value = m_albedo ? Float(m_albedo->eval(si0, true)[0]) : Float(0.f);
        if (dr::width(rho_value) != 1)
            return;
        FloatStorage rho = m_albedo ? broadcast_storage(rho_value, n) : m_rho_table,
                     tau = m_tau_given ? broadcast_storage(m_tau_o, n) : m_tau_table,
                     g = broadcast_storage(m_g, n),
                     c0_sq = dr::maximum(3.f * (1.f - rho) * (1.f - rho * g), 0.f),
                     s_c0 = powder::s_func(dr::sqrt(c0_sq), tau);
        m_volume_table_rho_given = (bool) m_albedo;
        // an albedo from the grain tables: optically thick (see optically_thick) when every
        // interval of the grid clears ThickLimit; then the records hold rho only
        m_volume_table_thick = !m_albedo && table_thickness(rho, tau) * (1.0 - SaturationMargin) >=
                                                ThickLimit;
        if (m_albedo) {
            m_volume = volume_constants(UnpolarizedSpectrum(rho_value),
                                        UnpolarizedSpectrum(0.f), m_g);
            dr::make_opaque(m_volume.rho, m_volume.rho2_3, m_volume.c0_sq, m_volume.c0);
        } else if (m_volume_table_thick) {
            // tau_o, which neither L2 nor C then reads, is its smallest value (as in
            // m_thick_volume); the other constants are computed per lane from rho
            m_volume.tau = UnpolarizedSpectrum(Float(dr::min(dr::detach(tau))));
            dr::make_opaque(m_volume.tau);
        }
        // (s(c0), tau_o) with a one-number albedo (rho and c0 in m_volume), (rho, s(c0),
        // tau_o, padding to a packet of 8) or, optically thick, (rho). (Records of tau_o
        // alone, with s(c0) computed in eval, made eval 1.16x slower: docs/benchmarks.md)
        std::vector<const FloatStorage *> quantities;
        if (m_albedo)
            quantities = { &s_c0, &tau };
        else if (m_volume_table_thick)
            quantities = { &rho };
        else
            quantities = { &rho, &s_c0, &tau, &tau };
        const uint32_t R = 2 * (uint32_t) quantities.size(); // entries per record
        std::vector<uint32_t> node(R * n), quantity(R * n);
        for (uint32_t i = 0; i < (uint32_t) n; ++i)
            for (uint32_t j = 0; j < R; ++j) {
                node[R * i + j] = std::min(i + (j & 1u), (uint32_t) n - 1);
                quantity[R * i + j] = j >> 1;
            }
        if constexpr (dr::is_jit_v<Float>) {
            using UInt32Storage = DynamicBuffer<UInt32>;
            UInt32Storage idx = dr::load<UInt32Storage>(node.data(), node.size()),
                          q = dr::load<UInt32Storage>(quantity.data(), quantity.size());
            FloatStorage table = dr::gather<FloatStorage>(*quantities.back(), idx);
            for (uint32_t k = (uint32_t) quantities.size() - 1; k-- > 0;)
                table = dr::select(q == k, dr::gather<FloatStorage>(*quantities[k], idx),
                                   table);
            m_volume_table = table;
            dr::make_opaque(m_volume_table);
        } else {
            std::vector<ScalarFloat> packed(R * n);
            for (size_t k = 0; k < packed.size(); ++k)
                packed[k] = (*quantities[quantity[k]])[node[k]];
            m_volume_table = dr::load<FloatStorage>(packed.data(), packed.size());
        }
        // lower bound of 2 c0 tau_o over the interpolated values (for the shortcuts of C)
        m_volume_table_x0 = 2.0 * std::sqrt(std::max(min_of(c0_sq), 0.0)) * min_of(tau);
        m_tabulated_volume = true;
    }

    /**
     * Lower bound of x0 = 2 c0 tau_o over the 1 nm grid with rho and tau_o interpolated
     * linearly between its nodes (and c0 from rho and the one g): on each interval, rho is at
     * most the larger of its two nodes, c0 (which decreases as rho grows, for every g in
     * [-1, 1]) at least c0 of that, and tau_o at least the smaller node.
     */
    double table_thickness(const FloatStorage &rho_, const FloatStorage &tau_) const {
        const uint32_t n = (uint32_t) dr::width(rho_);
        FloatStorage rho = dr::detach(rho_), tau = dr::detach(tau_);
        if constexpr (dr::is_jit_v<Float>) {
            UInt32 i = dr::arange<UInt32>(n), next = dr::minimum(i + 1u, n - 1u);
            Float rho_hi = dr::maximum(dr::gather<Float>(rho, i), dr::gather<Float>(rho, next)),
                  tau_lo = dr::minimum(dr::gather<Float>(tau, i), dr::gather<Float>(tau, next)),
                  g = dr::detach(m_g),
                  c0 = dr::sqrt(dr::maximum(3.f * (1.f - rho_hi) * (1.f - rho_hi * g), 0.f));
            return min_of(FloatStorage(2.f * c0 * tau_lo));
        } else {
            double x0 = powder_param::Inf, g = (double) m_g;
            for (uint32_t i = 0; i < n; ++i) {
                uint32_t j = std::min(i + 1, n - 1);
                double r = std::max((double) rho[i], (double) rho[j]),
                       t = std::min((double) tau[i], (double) tau[j]);
                x0 = std::min(x0, 2.0 * std::sqrt(std::max(3.0 * (1 - r) * (1 - r * g), 0.0)) * t);
            }
            return x0;
        }
    }

    /// n copies of a one-value parameter, differentiable (spectral volume table)
    static FloatStorage broadcast_storage(const Float &v, size_t n) {
        if constexpr (dr::is_jit_v<Float>)
            return v + dr::zeros<FloatStorage>(n);
        else
            return dr::full<FloatStorage>(v, n);
    }

    /// Smallest entry of a table (detached), as a double
    static double min_of(const FloatStorage &t) {
        if constexpr (dr::is_jit_v<Float>)
            return (double) dr::slice(dr::min(dr::detach(t)));
        else {
            double m = powder_param::Inf;
            for (size_t i = 0; i < t.size(); ++i)
                m = std::min(m, (double) t[i]);
            return m;
        }
    }

    /// Spectral variants: the volume constants per channel from m_volume_table (one
    /// packet gather per channel; linear in wavelength on the 1 nm grid)
    VolumeConstants lookup_volume(const SurfaceInteraction3f &si, Mask active) const {
        VolumeConstants k;
        if constexpr (is_spectral_v<Spectrum>) {
            UnpolarizedSpectrum t = table_position(si);
            // per channel, one packet of the two nodes of each quantity of a record;
            // assign(c, value) receives value(q), quantity q interpolated at channel c
            auto read = [&](auto packet, auto &&assign) {
                using Packet = decltype(packet);
                for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                    UInt32 i0 = UInt32(dr::floor(t[c]));
                    Packet v = dr::gather<Packet>(m_volume_table, i0, active);
                    Float w = t[c] - Float(i0);
                    assign(c, [&](size_t q) { return dr::lerp(v[2 * q], v[2 * q + 1], w); });
                }
            };
            // masked lanes read zeros: tau_o = 1 there keeps x = 2 c tau_o > 0 in the
            // closed forms of C (no 0 / 0 in lanes that are discarded anyway)
            auto unit_tau_in_masked_lanes = [&] { k.tau = dr::select(active, k.tau, 1.f); };
            if (m_volume_table_rho_given) { // records of (s(c0), tau_o)
                read(dr::Array<Float, 4>(), [&](size_t c, auto value) {
                    k.s_c0[c] = value(0);
                    k.tau[c] = value(1);
                });
                k.rho = m_volume.rho;
                k.rho2_3 = m_volume.rho2_3;
                k.c0_sq = m_volume.c0_sq;
                k.c0 = m_volume.c0;
                unit_tau_in_masked_lanes();
            } else {
                if (m_volume_table_thick) // records of rho
                    read(dr::Array<Float, 2>(),
                         [&](size_t c, auto value) { k.rho[c] = value(0); });
                else // records of (rho, s(c0), tau_o, padding)
                    read(dr::Array<Float, 8>(), [&](size_t c, auto value) {
                        k.rho[c] = value(0);
                        k.s_c0[c] = value(1);
                        k.tau[c] = value(2);
                    });
                // as volume_constants(rho, tau, g): the same c0 as the general path
                k.rho2_3 = 3.f * dr::square(k.rho);
                k.c0_sq = dr::maximum(3.f * (1.f - k.rho) * (1.f - k.rho * m_g), 0.f);
                k.c0 = dr::sqrt(k.c0_sq);
                if (m_volume_table_thick) { // s(c0) = 1 / (2 c0): see optically_thick
                    k.s_c0 = .5f / k.c0;
                    k.tau = m_volume.tau;
                }
                unit_tau_in_masked_lanes();
            }
        } else {
            DRJIT_MARK_USED(si);
            DRJIT_MARK_USED(active);
        }
        return k;
    }

    // --------------------------------------------------------------- energy

    /// Largest kappa / k0 inside the regime of enhanced back-scattering theory
    /// (narrow coherent cone), above which the constructor warns
    static constexpr double RegimeLimit = 0.25;

    /// Warn when kappa / k0 = kappa lambda / (2 pi) exceeds RegimeLimit at a wavelength
    /// the powder is evaluated at (k0 is smallest at the longest one): the rgb_wavelengths,
    /// `wavelength` (mono) or the spectral table's range
    void warn_outside_regime() const {
        double lam_nm;
        if constexpr (is_spectral_v<Spectrum>)
            lam_nm = TableMin + (TableSize - 1) * TableStep;
        else if constexpr (is_rgb_v<Spectrum>)
            lam_nm = std::max({ (double) m_rgb_wavelengths[0], (double) m_rgb_wavelengths[1],
                                (double) m_rgb_wavelengths[2] });
        else
            lam_nm = m_wavelength;
        double kappa = textured(powder_param::Extinction)
                           ? texture_values(powder_param::Extinction).hi : value_of(m_kappa),
               ratio = kappa * lam_nm * 1e-3 / (2.0 * M_PI);
        if (ratio > RegimeLimit)
            Log(Warn,
                "powder: property \"extinction\" = %g 1/um (its largest value) gives "
                "kappa/k0 = %.4g at %g nm, "
                "above the threshold 0.25: outside the narrow-cone regime of enhanced "
                "back-scattering theory (kappa/k0 << 1), where the coherent term is not "
                "physical (with energy=\"paper\" a white powder reflects more than it "
                "receives; see docs/powder.md, \"Energy\")",
                kappa, ratio, lam_nm);
    }

    /* energy = "conserving": the volume terms are multiplied by
         N(mu_i) = min(R_L, 1) / (R_L + R_C)   (per channel)
       with R_L and R_C the directional-hemispherical reflectances of A_v (L1 + L2) / (4 pi)
       and A_v C / (4 pi) at incidence mu_i, so that the volume part reflects min(R_L, 1).
       N is tabulated on NormMu incidences with sqrt(mu_k) uniform from NormS0 to 1 (mu_k
       from 4e-4 to 1, dense at grazing)
       per channel (RGB, mono) or per wavelength of a NormStep grid over the spectral table,
       and interpolated linearly (in sqrt(mu_i) and wavelength) by energy_norm. */
    static constexpr uint32_t NormMu = 24, NormPhi = 64, NormInner = 24, NormOuter = 24,
                              NormRadial = NormInner + NormOuter, NormQ = NormPhi * NormRadial;
    static constexpr float NormStep = 10.f; ///< nm, spectral variants
    static constexpr float NormS0 = .02f;   ///< sqrt(mu) of the first incidence node
    static constexpr uint32_t NormWavelengths = (uint32_t) ((TableSize - 1) / 10) + 1;

    /// Gauss-Legendre nodes and weights on (0, 1)
    static void gauss_legendre01(uint32_t n, ScalarFloat *x, ScalarFloat *w) {
        for (uint32_t i = 0; i < n; ++i) {
            double z = std::cos(M_PI * (i + 0.75) / (n + 0.5)), pp = 1.0;
            for (int it = 0; it < 100; ++it) {
                double p1 = 1.0, p2 = 0.0;
                for (uint32_t j = 1; j <= n; ++j) {
                    double p3 = p2;
                    p2 = p1;
                    p1 = ((2.0 * j - 1.0) * z * p2 - (j - 1.0) * p3) / j;
                }
                pp = n * (z * p1 - p2) / (z * z - 1.0);
                double z1 = z;
                z = z1 - p1 / pp;
                if (std::abs(z - z1) < 1e-15)
                    break;
            }
            x[i] = (ScalarFloat) (0.5 * (1.0 - z));
            w[i] = (ScalarFloat) (1.0 / ((1.0 - z * z) * pp * pp));
        }
    }

    /**
     * Node q of the quadrature of the projected disc at the incidence node `node`, in
     * polar coordinates (r, phi) about the back-scattering point c = wi_xy (where the
     * coherent cone sits): phi by the midpoint rule (NormPhi), r in [0, R(phi)] (R: the
     * rim) split at r1 = min(R, 0.05): Gauss-Legendre in log r on [r_min, r1] (the cone
     * can be 1e-3 wide), and in x on [r1, R] with r = R - (R - r1) x^2 (nodes dense at
     * the rim, where mu_o -> 0). Returns wi, wo and the weight of dA = mu_o dOmega.
     */
    std::tuple<Vector3f, Vector3f, Float> norm_node(const UInt32 &node, const UInt32 &q,
                                                    const FloatStorage &gx,
                                                    const FloatStorage &gw) const {
        UInt32 j = q / NormRadial, i = q - j * NormRadial;
        Float t = NormS0 + Float(node) * ((1.f - NormS0) / (NormMu - 1)), mu = t * t,
              mu2 = mu * mu,
              cx = dr::sqrt(1.f - mu2);
        auto [sin_p, cos_p] = dr::sincos((Float(j) + .5f) * (dr::TwoPi<ScalarFloat> / NormPhi));
        Float ce = cx * cos_p, root = dr::sqrt(dr::square(ce) + mu2);
        Mask ce_pos = ce > 0.f;
        // R = distance to the rim along e; Rp = R + 2 ce (> 0), both without cancellation
        Float R = dr::select(ce_pos, mu2 / (ce + root), root - ce),
              Rp = dr::select(ce_pos, ce + root, mu2 / (root - ce));
        Float r1 = dr::minimum(R, .05f), r_min = dr::minimum(1e-5f, .1f * r1);
        Float x = dr::gather<Float>(gx, i), w = dr::gather<Float>(gw, i);
        Mask inner = i < NormInner;
        Float L = dr::log(r1 / r_min), r_in = r_min * dr::exp(x * L), d = R - r1,
              r_out = R - d * dr::square(x);
        Float r = dr::select(inner, r_in, r_out),
              gap = dr::select(inner, R - r_in, d * dr::square(x)), // R - r
              weight = dr::select(inner, w * L * dr::square(r_in), 2.f * w * d * x * r_out) *
                       (dr::TwoPi<ScalarFloat> / NormPhi),
              // 1 - |c + r e|^2 = (R - r) (R + r + 2 c.e)
              mu_o = dr::sqrt(dr::maximum(gap * (Rp + r), 1e-14f));
        return { Vector3f(cx, 0.f, mu), Vector3f(cx + r * cos_p, r * sin_p, mu_o), weight };
    }

    /// N = min(R_L, 1) / (R_L + R_C) from the integrals RL, RC of L1 + L2 and C over the
    /// projected disc (without A_v / (4 pi)); 1 where the volume terms vanish
    Float norm_from(const Float &rl, const Float &rc) const {
        Float total = rl + rc, av_pos = dr::select(m_av > 0.f, m_av, 1.f),
              cap = dr::select(m_av > 0.f, 4.f * dr::Pi<ScalarFloat> / av_pos,
                               dr::Infinity<Float>);
        Mask ok = total > 0.f;
        return dr::select(ok, dr::minimum(rl, cap) / dr::select(ok, total, 1.f), 1.f);
    }

    /// Tabulate N (m_norm) for the configured volume lobes; differentiable
    void update_energy_norm() {
        if (!(m_single || m_multiple || m_coherent))
            return; // no volume term: eval never reads the table
        constexpr uint32_t C = (uint32_t) dr::size_v<UnpolarizedSpectrum>;
        const uint32_t NW = is_spectral_v<Spectrum> ? NormWavelengths : C,
                       G = (NW + C - 1) / C, n_blocks = G * NormMu;
        std::vector<ScalarFloat> x(NormRadial), w(NormRadial);
        gauss_legendre01(NormInner, x.data(), w.data());
        gauss_legendre01(NormOuter, x.data() + NormInner, w.data() + NormInner);
        FloatStorage gx = dr::load<FloatStorage>(x.data(), x.size()),
                     gw = dr::load<FloatStorage>(w.data(), w.size());
        Lobes lobes{ m_single, m_multiple, m_coherent, false };

        // wavelength (nm) of channel c of group g (spectral variants)
        auto group_wavelength = [&](const UInt32 &g, uint32_t c) {
            return TableMin + Float(dr::minimum(g * C + c, UInt32(NW - 1))) * NormStep;
        };
        DRJIT_MARK_USED(group_wavelength);

        if constexpr (dr::is_jit_v<Float>) {
            uint32_t n = n_blocks * NormQ;
            UInt32 lane = dr::arange<UInt32>(n), block = lane / NormQ,
                   q = lane - block * NormQ, group = block / NormMu,
                   node = block - group * NormMu;
            auto [wi, wo, weight] = norm_node(node, q, gx, gw);
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(n);
            si.wi = wi;
            if constexpr (is_spectral_v<Spectrum>)
                for (uint32_t c = 0; c < C; ++c)
                    si.wavelengths[c] = group_wavelength(group, c);
            VolumeConstants k = volume_constants(si, Mask(true));
            auto [ladder, coherent] = volume_terms(
                lobes, si, wi, wo, k, k0_over_kappa(inverse_wavelengths_um(si), si, true), true);
            UnpolarizedSpectrum norm;
            for (uint32_t c = 0; c < C; ++c)
                norm[c] = norm_from(dr::block_sum(ladder[c] * weight, NormQ),
                                    dr::block_sum(coherent[c] * weight, NormQ));
            // table index wl * NormMu + node, wl = g * C + c
            UInt32 t = dr::arange<UInt32>(NW * NormMu), wl = t / NormMu,
                   nd = t - wl * NormMu, g = wl / C, ch = wl - g * C,
                   src = g * NormMu + nd;
            Float table = dr::zeros<Float>(NW * NormMu);
            for (uint32_t c = 0; c < C; ++c)
                table = dr::select(ch == c, dr::gather<Float>(norm[c], src), table);
            m_norm = table;
            dr::make_opaque(m_norm);
        } else {
            std::vector<double> rl(n_blocks * C, 0.0), rc(n_blocks * C, 0.0);
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
            for (uint32_t b = 0; b < n_blocks; ++b) {
                uint32_t g = b / NormMu, node = b - g * NormMu;
                if constexpr (is_spectral_v<Spectrum>)
                    for (uint32_t c = 0; c < C; ++c)
                        si.wavelengths[c] = group_wavelength(g, c);
                for (uint32_t q = 0; q < NormQ; ++q) {
                    auto [wi, wo, weight] = norm_node(node, q, gx, gw);
                    si.wi = wi;
                    VolumeConstants k = volume_constants(si, Mask(true));
                    auto [ladder, coherent] = volume_terms(
                        lobes, si, wi, wo, k, k0_over_kappa(inverse_wavelengths_um(si), si, true),
                        true);
                    for (uint32_t c = 0; c < C; ++c) {
                        rl[b * C + c] += (double) ladder[c] * weight;
                        rc[b * C + c] += (double) coherent[c] * weight;
                    }
                }
            }
            std::vector<ScalarFloat> table(NW * NormMu);
            for (uint32_t wl = 0; wl < NW; ++wl)
                for (uint32_t nd = 0; nd < NormMu; ++nd) {
                    uint32_t b = (wl / C) * NormMu + nd, c = wl % C;
                    table[wl * NormMu + nd] =
                        norm_from((ScalarFloat) rl[b * C + c], (ScalarFloat) rc[b * C + c]);
                }
            m_norm = dr::load<FloatStorage>(table.data(), table.size());
        }
        pack_energy_norm();
    }

    /// Entries per record of m_records.norm: the 2 incidence nodes bracketing mu_i of every
    /// channel (RGB: 6, padded to 8; mono: 2), or of 2 x 2 (wavelength, incidence) nodes
    /// (spectral: 4, one record per channel)
    static constexpr size_t NormPacket =
        is_spectral_v<Spectrum> ? 4 : (dr::size_v<UnpolarizedSpectrum> == 3 ? 8 : 2);

    /// m_norm as records for one packet gather per lookup (gathers dominate the cost of
    /// eval on CPUs); differentiable through the gather from m_norm
    void pack_energy_norm() {
        constexpr uint32_t C = (uint32_t) dr::size_v<UnpolarizedSpectrum>, P = NormPacket;
        const uint32_t NW = is_spectral_v<Spectrum> ? NormWavelengths : C,
                       n_rec = is_spectral_v<Spectrum> ? NW * NormMu : NormMu;
        std::vector<uint32_t> src(P * n_rec);
        for (uint32_t r = 0; r < n_rec; ++r)
            for (uint32_t e = 0; e < P; ++e) {
                uint32_t k = r % NormMu, kk = std::min(k + (e & 1u), NormMu - 1);
                if (is_spectral_v<Spectrum>) {
                    uint32_t j = std::min(r / NormMu + (e >> 1), NW - 1);
                    src[P * r + e] = j * NormMu + kk;
                } else {
                    uint32_t c = std::min(e >> 1, C - 1); // padding repeats the last channel
                    src[P * r + e] = c * NormMu + kk;
                }
            }
        if constexpr (dr::is_jit_v<Float>) {
            using UInt32Storage = DynamicBuffer<UInt32>;
            m_records.norm = dr::gather<FloatStorage>(
                m_norm, dr::load<UInt32Storage>(src.data(), src.size()));
            dr::make_opaque(m_records.norm);
        } else {
            std::vector<ScalarFloat> packed(src.size());
            for (size_t i = 0; i < src.size(); ++i)
                packed[i] = m_norm[src[i]];
            m_records.norm = dr::load<FloatStorage>(packed.data(), packed.size());
        }
    }

    /// N at incidence mu_i and the channel wavelengths lam (um): linear interpolation of
    /// m_norm in sqrt(mu_i) (and in wavelength, spectral variants)
    UnpolarizedSpectrum energy_norm(const Float &mu_i, const UnpolarizedSpectrum &lam,
                                    Mask active) const {
        Float t = dr::clip((dr::sqrt(mu_i) - NormS0) * ((NormMu - 1) / (1.f - NormS0)), 0.f,
                           (ScalarFloat) NormMu - 1.001f);
        UInt32 k0 = UInt32(t);
        Float w = t - Float(k0);
        UnpolarizedSpectrum out(0.f);
        using Packet = dr::Array<Float, NormPacket>;
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                Float s = dr::clip((lam[c] * 1e3f - TableMin) * (1.f / NormStep), 0.f,
                                   (ScalarFloat) NormWavelengths - 1.001f);
                UInt32 j0 = UInt32(s);
                Float v = s - Float(j0);
                Packet e = dr::gather<Packet>(m_records.norm, j0 * NormMu + k0, active);
                out[c] = dr::lerp(dr::lerp(e[0], e[1], w), dr::lerp(e[2], e[3], w), v);
            }
        } else {
            DRJIT_MARK_USED(lam);
            Packet e = dr::gather<Packet>(m_records.norm, k0, active);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                out[c] = dr::lerp(e[2 * c], e[2 * c + 1], w);
        }
        return out;
    }

    /**
     * The volume terms of docs/model.md Eq. 9 (without A_v / (4 pi)) for the enabled lobes:
     * (L1 + L2, C), the ladder and the cyclical (coherent) term, at the directions wi, wo
     * (mu_i, mu_o > 0), with the volume constants k and k0 / kappa per channel; g,
     * kappa and d of the interaction si.
     */
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    volume_terms(const Lobes &lobes, const SurfaceInteraction3f &si, const Vector3f &wi,
                 const Vector3f &wo, const VolumeConstants &k,
                 const UnpolarizedSpectrum &k0_kappa, Mask active) const {
        Float mu_i = Frame3f::cos_theta(wi), mu_o = Frame3f::cos_theta(wo),
              mu_sum = mu_i + mu_o, mu_prod = mu_i * mu_o,
              h = mu_prod / mu_sum; // = 1 / (2 v), docs/model.md Eq. 10b
        UnpolarizedSpectrum ladder(0.f), coherent(0.f);

        if (lobes.single) {
            /* L1, docs/model.md Eq. 9a:
               rho P(Theta) / (mu_i + mu_o) [1 - exp(-kappa d (1/mu_i + 1/mu_o))]
               with the Henyey-Greenstein P = (1 - g^2) / t^(3/2),
               t = 1 + g^2 - 2 g cos(Theta), cos(Theta) = -dot(wi, wo),
               rewritten with non-negative terms so that it keeps its
               precision when |g| -> 1: with sg = sign(g) (+1 at g = 0),
               t = (1 - |g|)^2 + |g| |wi + sg wo|^2
               (|g| written as sg g: the derivative of dr::abs at g = 0 is 0,
               which gave a wrong d/dg at the default g = 0) */
            Float g = at(powder_param::G, si, active),
                  sg = dr::select(g >= 0.f, 1.f, -1.f), abs_g = sg * g,
                  t = dr::square(1.f - abs_g) +
                      abs_g * dr::squared_norm(dr::fmadd(sg, wo, wi)),
                  // P(Theta) / (mu_i + mu_o) as one division
                  factor = (1.f - dr::square(g)) / (t * dr::sqrt(t) * mu_sum);
            if (m_finite_thickness) {
                // lanes of infinite thickness (one value per lane) get 1, and no 0 * inf
                // in the gradient of the extinction
                Float d = at(powder_param::Thickness, si, active);
                Mask infinite = dr::isinf(d);
                factor *= dr::select(infinite, 1.f,
                                     powder::one_minus_exp_neg(
                                         at(powder_param::Extinction, si, active) *
                                         dr::select(infinite, 0.f, d) *
                                         (dr::rcp(mu_i) + dr::rcp(mu_o))));
            }
            UnpolarizedSpectrum L1 = k.rho * factor;
            ladder += L1;
        }

        if (lobes.multiple) {
            // L2, docs/model.md Eq. 9b (corrected):
            // 3 rho^2 [s(c0) + mu_i mu_o / (mu_i + mu_o)] / ((1 + c0 mu_i) (1 + c0 mu_o))
            UnpolarizedSpectrum L2 = k.rho2_3 * (k.s_c0 + h) /
                                     ((1.f + k.c0 * mu_i) * (1.f + k.c0 * mu_o));
            ladder += L2;
        }

        if (lobes.coherent) {
            /* C, docs/model.md Eq. 9c with Eq. 10:
               3 rho^2 [1/(2v) + s(c)] / (mu_i mu_o ((c + v)^2 + u^2)),
               alpha = (k0 / kappa) |wo_xy - wi_xy|, c = sqrt(c0^2 + alpha^2),
               u = (k0 / kappa) (mu_i - mu_o), 1/(2v) = h. The denominator written
               without 1/mu (no square root of mu_i mu_o, one division fewer): with
               p = 2 mu_i mu_o, 4 mu_i mu_o [mu_i mu_o ((c + v)^2 + u^2)] =
               (c p + mu_i + mu_o)^2 + (k0 / kappa)^2 ((mu_i - mu_o) p)^2 =: D, so
               C = 3 rho^2 2 p [h + s(c)] / D, with h + s(c) = [h x + tau (1 - exp(-x))] / x,
               x = 2 c tau (s(c) as powder::s_func, its series below x = 0.03) */
            Float dx = wo.x() - wi.x(), dy = wo.y() - wi.y(), p = 2.f * mu_prod,
                  up2 = dr::square((mu_i - mu_o) * p);
            UnpolarizedSpectrum k0_kappa2 = dr::square(k0_kappa),
                c = dr::sqrt(k.c0_sq + k0_kappa2 * (dx * dx + dy * dy)),
                D = dr::square(dr::fmadd(c, p, mu_sum)) + k0_kappa2 * up2,
                x = c * (2.f * k.tau), prefactor = k.rho2_3 * (2.f * p), C;
            if (m_coherent_saturated) {
                // x >= 18 everywhere: 1 - exp(-x) == 1; or optically thick (within 2^-18 of
                // 1): s(c) = 1 / (2 c), whatever tau_o > 0 (here its smallest value)
                C = prefactor * dr::fmadd(h, x, k.tau) / (x * D);
            } else if (!m_coherent_series) { // x >= 0.03 everywhere: no series
                C = prefactor *
                    dr::fmadd(h, x, k.tau * (1.f - powder::exp_neg(dr::minimum(x, 20.f)))) /
                    (x * D);
            } else {
                auto small = x < (ScalarFloat) CoherentSeriesLimit;
                UnpolarizedSpectrum xs = dr::select(small, x, 0.f),
                                    xl = dr::select(small, 1.f, x),
                    series = powder::one_minus_exp_neg_over_x_series(xs),
                    // (the clamp as in powder::one_minus_exp_neg: no value changes)
                    one_minus_e = 1.f - powder::exp_neg(dr::minimum(xl, 20.f)),
                    num = dr::select(small, h + k.tau * series,
                                     dr::fmadd(h, xl, k.tau * one_minus_e));
                C = prefactor * num / (xl * D);
            }
            coherent = C;
        }
        return { ladder, coherent };
    }

    /**
     * The BRDF (without the cosine factor) of docs/model.md, Eq. 23, for the enabled
     * lobes: f = A_v (L1 + L2 + C) / (4 pi) + S. Outside `active`, the cosines
     * mu_i and mu_o are replaced by 1, so that no lane divides by 0 (every term is
     * finite for finite x and y components); the values of those lanes are
     * meaningless, and the callers (eval, eval_pdf_impl) set them to 0 after the
     * cosine factor, which also keeps them out of every gradient
     * (tests/test_autodiff.py). Only the cosines: a select of the x and y components
     * with the mask compiles to masked loads, which wait for the cosines' loads and
     * the comparison; on batches beyond the caches that made the whole eval 1.5-1.7x
     * slower, 2.6x with one thread (docs/benchmarks.md, issue 11's step 5).
     */
    UnpolarizedSpectrum eval_brdf(const Lobes &lobes, const SurfaceInteraction3f &si,
                                  const Vector3f &wo_, const UnpolarizedSpectrum &lam,
                                  Mask active) const {
        Vector3f wi(si.wi.x(), si.wi.y(), dr::select(active, si.wi.z(), 1.f)),
                 wo(wo_.x(), wo_.y(), dr::select(active, wo_.z(), 1.f));
        Float mu_i = Frame3f::cos_theta(wi), mu_sum = mu_i + Frame3f::cos_theta(wo);

        UnpolarizedSpectrum result(0.f),
            inv_lam = inverse_wavelengths_um(si); // 1 / lambda (1/um), for k0 / kappa and S

        if (lobes.single || lobes.multiple || lobes.coherent) {
            VolumeConstants k = volume_constants(si, active);
            auto [ladder, coherent] = volume_terms(lobes, si, wi, wo, k,
                                                   k0_over_kappa(inv_lam, si, active), active);
            UnpolarizedSpectrum volume = ladder + coherent; // L1 + L2 + C
            if (m_conserving) // energy = "conserving": times N(mu_i), per channel
                volume *= energy_norm(mu_i, lam, active);
            result = volume * (at(powder_param::AmplitudeVolume, si, active) *
                               dr::InvFourPi<ScalarFloat>);
        }

        if (lobes.surface) {
            UnpolarizedSpectrum S;
            Float as = at(powder_param::AmplitudeSurface, si, active);
            if (m_specular == SpecularModel::HarveyShack) {
                /* S, docs/model.md Eq. 21-22 (Harvey-Shack, Gaussian PSD):
                   A_s' (4 pi^2 / lam^4) (mu_i + mu_o)^2 pi l_c^2 exp(-pi^2 l_c^2 f_s^2),
                   f_s = |wo_xy + wi_xy| / lam */
                Float sx = wo.x() + wi.x(), sy = wo.y() + wi.y(),
                      lc2 = dr::square(at(powder_param::CorrelationLength, si, active)),
                      // the factors that do not depend on lambda, grouped so that the
                      // parameters' product is computed once per kernel, not per lane
                      prefactor = (as * (4.f * dr::Pi<ScalarFloat> * dr::square(dr::Pi<ScalarFloat>)) *
                                   lc2) * dr::square(mu_sum),
                      // pi^2 l_c^2 |wo_xy + wi_xy|^2 / ln 2 (exp2_neg takes base-2 exponents)
                      t = (dr::square(dr::Pi<ScalarFloat>) * dr::InvLogTwo<ScalarFloat> * lc2) *
                          (sx * sx + sy * sy);
                UnpolarizedSpectrum inv_lam2 = dr::square(inv_lam);
                S = prefactor * dr::square(inv_lam2) * powder::exp2_neg(t * inv_lam2);
            } else {
                /* S, docs/model.md Eq. 20 (Gaussian in the angle theta_s to the mirror
                   direction): A_s / (sigma sqrt(2 pi)) exp(-theta_s^2 / (2 sigma^2)) */
                Float theta = mirror_angle(wi, wo),
                      sigma = at(powder_param::Sigma, si, active);
                S = as * dr::InvSqrtTwoPi<ScalarFloat> / sigma *
                    powder::exp_neg(dr::square(theta) / (2.f * dr::square(sigma)));
            }
            if (m_surface_fresnel) // surface_fresnel: S F(c) / F(1), c = wi . h
                S *= surface_fresnel_factor(si, powder::half_vector_cosine(dr::dot(wi, wo)),
                                            active);
            result += S;
        }

        return result;
    }

    /// Angle between wo and the mirror direction of wi (stable near 0)
    static Float mirror_angle(const Vector3f &wi, const Vector3f &wo) {
        return powder::angle_between(wo, Vector3f(-wi.x(), -wi.y(), wi.z()));
    }

    // ------------------------------------------------------------ sampling

    LobeWeights lobe_weights(const SurfaceInteraction3f &si, Float lam_mean,
                             const Lobes &lobes) const {
        Float mu = dr::maximum(Frame3f::cos_theta(si.wi), 1e-4f);
        auto value = [&](powder_param::Id p) { return dr::detach(at(p, si, true)); };
        Float av = value(powder_param::AmplitudeVolume), rho = dr::clip(m_rho_mean, 0.f, 1.f),
              g = value(powder_param::G), kappa = value(powder_param::Extinction),
              tau = m_tau_mean, as = value(powder_param::AmplitudeSurface);

        // Rough estimates of each term's directional albedo (integral of
        // f cos over the hemisphere = integral of f over the projected disc)
        Float c0 = dr::safe_sqrt(3.f * (1.f - rho) * (1.f - rho * g));
        Float s0 = powder::s_func(c0, tau);
        Float e_diffuse = 0.f, e_coherent = 0.f, e_surface = 0.f;
        if (lobes.single)
            e_diffuse += av * .25f * rho / (mu + .5f);
        if (lobes.multiple)
            e_diffuse += av * .25f * 3.f * dr::square(rho) * (s0 + h_of(mu, .5f)) /
                         ((1.f + c0 * mu) * (1.f + .5f * c0));

        // Width of the cone in the projected plane: C falls off where
        // alpha ~ c0 + v, i.e. |wo_xy - wi_xy| ~ (kappa / k0) (c0 + 1 / mu_i).
        // Broader cones are left to the cosine lobe.
        Float width_c = dr::minimum(
            .5f * kappa * lam_mean * dr::InvTwoPi<ScalarFloat> * (c0 + dr::rcp(mu)), .25f);
        if (lobes.coherent) {
            Float peak = 3.f * dr::square(rho) * (s0 + .5f * mu) / dr::square(1.f + c0 * mu);
            e_coherent = av * .25f * peak * dr::square(width_c);
        }

        Float width_s, wide = 0.f;
        if (m_specular == SpecularModel::HarveyShack) {
            width_s = lam_mean * dr::InvPi<ScalarFloat> * dr::InvSqrtTwo<ScalarFloat> /
                      value(powder_param::CorrelationLength);
            // Truncated to the disc, a lobe much wider than the disc tends to the
            // uniform disc, which is the cosine lobe; the chord lobe (powder_lobes.h)
            // tends to 1 / (4 sqrt(1 - u^2)) instead, whose peaks at the ends of the
            // short chords a quadrature resolves poorly. So a share 1 - (0.4 / width)^2
            // of the surface lobe's probability goes to the cosine lobe: none for widths
            // up to 0.4 (l_c >= 0.3 um); wider lobes have S > 0 on the whole disc
            // (exponent at most (1 + |c|)^2 / (2 width^2) < 13), so that these cosine
            // samples never have weight 0
            wide = dr::maximum(1.f - dr::square(.4f / width_s), 0.f);
            // S integrated over the projected plane, times the share of a centred
            // Gaussian of this width inside the unit disc (small l_c: wide lobes
            // carry little energy onto the hemisphere)
            if (lobes.surface)
                e_surface = 16.f * dr::square(dr::Pi<ScalarFloat>) * as * dr::square(mu) /
                            dr::square(lam_mean) *
                            powder::one_minus_exp_neg(.5f / dr::square(width_s));
        } else {
            width_s = value(powder_param::Sigma);
            if (lobes.surface)
                e_surface = as * width_s * dr::SqrtTwoPi<ScalarFloat> * mu;
        }

        // surface_fresnel: the lobe's energy follows the factor F(mu_i) / F(1) of the
        // mirror direction (channel mean), so that its share of the samples grows with it
        // towards grazing light
        if (lobes.surface && m_surface_fresnel) {
            UnpolarizedSpectrum f = dr::detach(surface_fresnel_factor(si, mu, true));
            Float mean = 0.f;
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                mean += f[c];
            e_surface *= mean * (1.f / (ScalarFloat) dr::size_v<UnpolarizedSpectrum>);
        }

        Float total = e_diffuse + e_coherent + e_surface;
        Mask positive = total > 0.f;
        Float inv_total = dr::select(positive, dr::rcp(total), 0.f);
        LobeWeights w;
        // Probabilities in proportion to the estimated energies, no floors: a
        // lobe with little energy gets few samples. (Floors of 10 % made the
        // weights bimodal and, for a near-Lambertian powder under broad light,
        // up to 25x noisier than cosine sampling; see docs/benchmarks.md.) The
        // cosine lobe keeps at least 10 %, but for the surface term alone: S is
        // exactly 0 beyond ~9 widths of its lobe (exp2_neg's cut), so cosine
        // samples there had weight 0 (8-10 % of all samples for l_c = 3-10 um),
        // and nothing else is left to sample.
        bool surface_only = lobes.surface && !lobes.single && !lobes.multiple && !lobes.coherent;
        w.coherent = lobes.coherent && !m_cosine_only
            ? Float(.9f * e_coherent * inv_total) : Float(0.f);
        w.surface = !lobes.surface || m_cosine_only ? Float(0.f)
                    : surface_only ? dr::select(as > 0.f, 1.f - wide, 0.f)
                                   : dr::select(as > 0.f, .9f * e_surface * inv_total, 0.f) *
                                         (1.f - wide);
        w.width_coherent = width_c;
        w.width_surface = width_s;
        return w;
    }

    static Float h_of(Float a, Float b) { return a * b / (a + b); }

    /// Coherent lobe: a 2D Cauchy law of wo_xy - wi_xy with scale b, truncated
    /// to the projected disc chord by chord (powder_lobes.h)
    static Vector3f sample_coherent(const Vector3f &wi, Float b, const Point2f &u) {
        return powder::sample_projected<powder::Radial::Cauchy>(
            wi.x(), wi.y(), dr::square(Frame3f::cos_theta(wi)), b, Float(0.f), u);
    }

    static Float pdf_coherent(const Vector3f &wi, const Vector3f &wo, Float b) {
        return powder::pdf_projected<powder::Radial::Cauchy>(
            wi.x(), wi.y(), dr::square(Frame3f::cos_theta(wi)), b, Float(0.f), wo);
    }

    /// Surface lobe. Harvey-Shack: a 2D Gaussian of wo_xy + wi_xy (the spatial
    /// frequency times lambda, docs/model.md Eq. 21-22) truncated to the projected disc
    /// chord by chord, moved inwards to follow the factor (mu_i + mu_o)^2; Gaussian: a
    /// Gaussian in the cylindrical equal-area coordinates about the axis perpendicular
    /// to the plane of incidence, truncated at the horizon (powder_lobes.h)
    Vector3f sample_surface(const Vector3f &wi, Float width, const Point2f &u) const {
        if (m_specular == SpecularModel::HarveyShack)
            return powder::sample_projected<powder::Radial::Gaussian>(
                -wi.x(), -wi.y(), dr::square(Frame3f::cos_theta(wi)), width,
                surface_shift(wi, width), u);
        return powder::sample_angular(Vector3f(-wi.x(), -wi.y(), wi.z()), width, u);
    }

    Float pdf_surface(const Vector3f &wi, const Vector3f &wo, Float width) const {
        if (m_specular == SpecularModel::HarveyShack)
            return powder::pdf_projected<powder::Radial::Gaussian>(
                -wi.x(), -wi.y(), dr::square(Frame3f::cos_theta(wi)), width,
                surface_shift(wi, width), wo);
        return powder::pdf_angular(Vector3f(-wi.x(), -wi.y(), wi.z()), width, wo);
    }

    /// Shift of the Harvey-Shack lobe towards the zenith (powder::projected_shift)
    static Float surface_shift(const Vector3f &wi, Float width) {
        return powder::projected_shift(dr::sqrt(dr::square(wi.x()) + dr::square(wi.y())),
                                       Frame3f::cos_theta(wi), width);
    }

    Float pdf_impl(const Lobes &lobes, const SurfaceInteraction3f &si, const Vector3f &wo,
                   const LobeWeights &w, Mask active) const {
        Float mu_o = Frame3f::cos_theta(wo);
        Float pdf = (1.f - w.coherent - w.surface) * dr::InvPi<ScalarFloat> * mu_o;
        if (lobes.coherent)
            pdf += w.coherent * pdf_coherent(si.wi, wo, w.width_coherent);
        if (lobes.surface)
            pdf += w.surface * pdf_surface(si.wi, wo, w.width_surface);
        return dr::select(active && mu_o > 0.f, pdf, 0.f);
    }

    std::pair<UnpolarizedSpectrum, Float>
    eval_pdf_impl(const Lobes &lobes, const SurfaceInteraction3f &si, const Vector3f &wo,
                  const LobeWeights &w, Mask active) const {
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        UnpolarizedSpectrum value =
            eval_brdf(lobes, si, wo, wavelengths_um(si), active) * Frame3f::cos_theta(wo);
        Float pdf = pdf_impl(lobes, si, wo, w, active);
        return { dr::select(active, value, 0.f), pdf };
    }

    // ------------------------------------------------------ input checking

    /// The value of a parameter that holds one value (lane 0 of a JIT array)
    template <typename T> static double value_of(const T &v) {
        return (double) dr::slice(v);
    }

    /// The member holding a float parameter of the table powder_param::Table
    static Float Powder::*member(powder_param::Id p) {
        static constexpr Float Powder::*members[powder_param::Count] = {
            &Powder::m_av, &Powder::m_g, &Powder::m_kappa, &Powder::m_tau_o,
            &Powder::m_thickness, &Powder::m_as, &Powder::m_lc, &Powder::m_sigma,
            &Powder::m_radius, &Powder::m_radius2, &Powder::m_fraction2,
            &Powder::m_agglomerate_radius, &Powder::m_agglomerate_fill
        };
        return members[p];
    }

    /// Whether a parameter enters the model as configured (and is range-checked)
    bool in_use(powder_param::Id p) const {
        switch (p) {
            case powder_param::TauO: return m_tau_given;
            case powder_param::Radius: return !m_albedo && !agglomerate();
            case powder_param::Radius2:
            case powder_param::Fraction2: return !m_albedo && m_two_populations;
            case powder_param::AgglomerateRadius:
            case powder_param::AgglomerateFill: return !m_albedo && agglomerate();
            case powder_param::CorrelationLength:
                return m_specular == SpecularModel::HarveyShack;
            case powder_param::Sigma: return m_specular == SpecularModel::Gaussian;
            default: return true;
        }
    }

    bool agglomerate() const { return m_grain_model == powder::GrainModel::Agglomerate; }

    /// Whether a float parameter is given as a texture
    bool textured(powder_param::Id p) const { return (bool) m_textures[p]; }

    /// A float parameter at an interaction: its texture at si.uv, or its value
    Float at(powder_param::Id p, const SurfaceInteraction3f &si, Mask active) const {
        if (m_textures[p])
            return m_textures[p]->eval_1(si, active);
        DRJIT_MARK_USED(si);
        DRJIT_MARK_USED(active);
        return this->*member(p);
    }

    /// The values a parameter's texture holds (TextureValues)
    TextureValues<Float, Spectrum> texture_values(powder_param::Id p) const {
        TextureValues<Float, Spectrum> values;
        // (traverse() only reads here; Mitsuba declares it non-const)
        const_cast<Texture *>(m_textures[p].get())->traverse(&values);
        return values;
    }

    /**
     * Check every value a parameter's texture holds against the parameter's range
     * (a thickness texture must be finite); a texture that exposes no values is
     * accepted with a warning, and one that is not supported as a texture (the grain
     * parameters) is an error
     */
    void check_texture(powder_param::Id p) const {
        const powder_param::Spec &spec = powder_param::Table[p];
        TextureValues<Float, Spectrum> values = texture_values(p);
        if (!values.found) {
            Log(Warn, "powder: the texture of property \"%s\" exposes no values, so its "
                      "range %s cannot be checked", spec.name, range_string(spec.range));
            return;
        }
        powder_param::Range range = spec.range;
        if (p == powder_param::Thickness)
            range.hi_closed = false; // finite: see m_finite_thickness
        if (values.nan || !range.contains(values.lo) || !range.contains(values.hi))
            Throw("powder: property \"%s\" is a texture with values from %g to %g%s; valid "
                  "range is %s", spec.name, values.lo, values.hi,
                  values.nan ? " and NaN" : "", range_string(range));
    }

    static std::string range_string(const powder_param::Range &r) {
        std::ostringstream oss;
        oss << (r.lo_closed ? "[" : "(") << r.lo << ", " << r.hi << (r.hi_closed ? "]" : ")");
        return oss.str();
    }

    /// Whether mi.traverse exposes a parameter: those in use
    bool exposed(powder_param::Id p) const { return in_use(p); }

    void check_albedo() const {
        ScalarFloat max_value;
        bool has_max = true;
        try {
            max_value = m_albedo->max();
        } catch (const std::exception &) {
            has_max = false; // this texture type cannot report its maximum
        }
        if (has_max && !(max_value <= 1.f + 1e-5f))
            Throw("powder: property \"albedo\" has a maximum of %g; a "
                  "single-scattering albedo must lie in [0, 1]", (double) max_value);
        if (!m_albedo->is_spatially_varying()) {
            ScalarFloat min_value;
            try {
                min_value = albedo_minimum();
            } catch (const std::exception &) {
                return; // this texture type cannot be evaluated in this variant
            }
            if (!(min_value >= 0.f))
                Throw("powder: property \"albedo\" has a minimum of %g; a "
                      "single-scattering albedo must lie in [0, 1]", (double) min_value);
        }
    }

    /// Smallest value of a spatially uniform albedo (over the spectral table's
    /// wavelengths in spectral variants), detached
    ScalarFloat albedo_minimum() const {
        ScalarFloat result = std::numeric_limits<ScalarFloat>::infinity();
        int steps = is_spectral_v<Spectrum> ? (TableSize + 3) / 4 : 1;
        for (int i = 0; i < steps; ++i) {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(1);
            if constexpr (is_spectral_v<Spectrum>) {
                for (size_t j = 0; j < 4; ++j)
                    si.wavelengths[j] = dr::minimum(TableMin + (4 * i + j) * TableStep,
                                                    TableMin + (TableSize - 1) * TableStep);
            }
            UnpolarizedSpectrum v = dr::detach(m_albedo->eval(si));
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
                ScalarFloat x;
                if constexpr (dr::is_jit_v<Float>)
                    x = dr::slice(v[j], 0);
                else
                    x = v[j];
                result = std::min(result, x);
            }
        }
        return result;
    }

    void parse_lobes(const std::string &spec) {
        m_single = m_multiple = m_coherent = m_surface = false;
        std::vector<std::string> names = tokenize(spec);
        if (names.empty())
            Throw("powder: property \"lobes\" = \"%s\" names no lobe; valid names "
                  "are single, multiple, coherent, surface (or all)", spec);
        for (const std::string &n : names) {
            if (n == "all")
                m_single = m_multiple = m_coherent = m_surface = true;
            else if (n == "single")
                m_single = true;
            else if (n == "multiple")
                m_multiple = true;
            else if (n == "coherent")
                m_coherent = true;
            else if (n == "surface")
                m_surface = true;
            else
                Throw("powder: property \"lobes\" = \"%s\" contains the unknown lobe "
                      "\"%s\"; valid names are single, multiple, coherent, surface "
                      "(or all)", spec, n);
        }
    }

    std::string lobes_string() const {
        std::vector<std::string> names;
        if (m_single) names.push_back("single");
        if (m_multiple) names.push_back("multiple");
        if (m_coherent) names.push_back("coherent");
        if (m_surface) names.push_back("surface");
        std::string out;
        for (size_t i = 0; i < names.size(); ++i)
            out += (i ? "," : "") + names[i];
        return out;
    }

    void parse_rgb_wavelengths(const std::string &spec) {
        std::vector<std::string> items = tokenize(spec);
        if (items.size() != 3)
            Throw("powder: property \"rgb_wavelengths\" = \"%s\" must hold exactly 3 "
                  "wavelengths in nm (R, G, B), got %zu", spec, items.size());
        for (size_t i = 0; i < 3; ++i) {
            char *end = nullptr;
            double v = std::strtod(items[i].c_str(), &end);
            if (end == items[i].c_str() || *end != '\0')
                Throw("powder: property \"rgb_wavelengths\" = \"%s\": \"%s\" is not a "
                      "number", spec, items[i]);
            if (!(v > 0.0) || !std::isfinite(v))
                Throw("powder: property \"rgb_wavelengths\" = \"%s\": wavelength %g is "
                      "out of range; valid range is (0, inf) nm", spec, v);
            m_rgb_wavelengths[i] = (ScalarFloat) v;
        }
    }

    static std::vector<std::string> tokenize(const std::string &s) {
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

private:
    ref<Texture> m_albedo;                          ///< null: albedo from Mie theory
    Float m_av, m_g, m_kappa, m_tau_o, m_thickness, m_as, m_lc, m_sigma;
    ref<Texture> m_textures[powder_param::Count]; ///< texture-valued float parameters
    Float m_radius, m_radius2, m_fraction2;
    Float m_agglomerate_radius, m_agglomerate_fill;
    /// spatially varying grains: efficiency table (grain_efficiencies)
    powder::EfficiencyTable m_grain_table;
    FloatStorage m_grain_records;
    double m_grain_table_lo = 0.0, m_grain_table_hi = 0.0, m_grain_rho_mean = 0.5;
    double m_grain_table_held = 0.0; ///< agglomerates: the held property's value in the table
    ScalarFloat m_grain_u0 = 0.f, m_grain_du = 1.f;
    powder::GrainModel m_grain_model = powder::GrainModel::Sphere;
    powder::Mixing m_mixing = powder::Mixing::Bruggeman;
    Float m_rho_mean, m_tau_mean;
    bool m_tau_given = false, m_two_populations = false;
    powder::OpticalTable m_optics;
    std::vector<double> m_table_wavelengths;       ///< nm
    std::vector<std::complex<double>> m_index;     ///< n + i k at those wavelengths
    UnpolarizedSpectrum m_k0_kappa = 0.f; ///< RGB and mono: k0 / kappa per channel
    FloatStorage m_packed;          ///< spectral: grain tables for lookup_grains
    /// when m_uniform_volume (rho, c0: m_volume_table_rho_given; m_thick_volume: tau_o is the
    /// smallest of the table, read by nothing but the bound x0)
    VolumeConstants m_volume;
    bool m_uniform_volume = false;
    /// 2 c0 tau_o >= 18 in every channel, or m_thick_volume
    bool m_coherent_saturated = false;
    /// spectral: m_uniform_volume because the layer is optically thick (optically_thick)
    bool m_thick_volume = false;
    bool m_coherent_series = true;     ///< some 2 c0 tau_o < CoherentSeriesLimit
    /// spectral: (rho, s(c0), tau_o) on the 1 nm grid (update_volume_table)
    FloatStorage m_volume_table;
    bool m_tabulated_volume = false;
    bool m_volume_table_rho_given = false; ///< records of (s(c0), tau_o) only
    /// records of rho only: an albedo from the grain tables, optically thick at every
    /// wavelength (table_thickness; s(c0) = 1 / (2 c0), tau_o in m_volume.tau)
    bool m_volume_table_thick = false;
    bool m_tau_table_constant = false;     ///< every entry of m_tau_table is the same
    double m_volume_table_x0 = 0.0; ///< smallest 2 c0 tau_o of m_volume_table
    /// RGB and mono: the entries of m_rho_table and m_tau_table, one per channel
    UnpolarizedSpectrum m_rho_channels = 0.f, m_tau_channels = 0.f;
    FloatStorage m_rho_table, m_tau_table, m_qext_table, m_qsca_table, m_qext2_table,
        m_qsca2_table;
    SpecularModel m_specular;
    bool m_surface_fresnel = false; ///< surface_fresnel = "fresnel"
    bool m_fresnel_constant = false; ///< surface_fresnel: one index at every wavelength
    /// surface_fresnel: RGB and mono: eta, k and 1 / F(1) per channel (literal constants:
    /// they never change after construction); spectral: records (eta[i], eta[i + 1], k[i],
    /// k[i + 1]) of the 1 nm grid (set_fresnel_index)
    UnpolarizedSpectrum m_fresnel_eta = 0.f, m_fresnel_k = 0.f, m_fresnel_inv_f1 = 0.f;
    bool m_cosine_only = false;
    bool m_conserving = false;      ///< energy = "conserving"
    /// energy = "conserving": the factor N per wavelength (RGB/mono: channel) and mu_i
    /// node, at index wavelength * NormMu + node (update_energy_norm)
    FloatStorage m_norm;
    /// Records read by eval (one traversal entry for both): m_norm as records for
    /// energy_norm (pack_energy_norm), and the surface_fresnel index (set_fresnel_index)
    struct Records {
        FloatStorage norm, fresnel;
        DRJIT_STRUCT(Records, norm, fresnel)
    } m_records;
    bool m_single, m_multiple, m_coherent, m_surface;
    bool m_finite_thickness = false;
    uint32_t m_comp_volume = 0, m_comp_coherent = 0, m_comp_surface = 0;
    ScalarFloat m_wavelength;
    ScalarFloat m_rgb_wavelengths[3];

    MI_TRAVERSE_CB(Base, m_albedo, m_textures, m_av, m_g, m_kappa, m_tau_o, m_thickness, m_as,
                   m_lc, m_sigma, m_radius, m_radius2, m_fraction2, m_agglomerate_radius,
                   m_agglomerate_fill, m_rho_mean, m_tau_mean,
                   m_rho_channels, m_tau_channels, m_k0_kappa, m_packed, m_volume, m_volume_table,
                   m_rho_table, m_tau_table, m_qext_table, m_qsca_table, m_qext2_table,
                   m_qsca2_table, m_records, m_grain_records)
};

NAMESPACE_END(mitsuba)

// ---------------------------------------------------------------------------
//  Registration. CMake compiles this file once per Mitsuba variant with
//  POWDER_VARIANT=<name> and its types (POWDER_BACKEND_<scalar|llvm|cuda>,
//  POWDER_CHANNELS = 3 (RGB), 1 (mono) or 0 (spectral), POWDER_POLARIZED), so
//  that the variants build in parallel and incrementally, and once with
//  POWDER_REGISTRY for the plugin entry point, which registers every variant of
//  the generated list powder_variants.h (CMakeLists.txt: POWDER_VARIANTS).
// ---------------------------------------------------------------------------

#define POWDER_CAT_(a, b) a##b
#define POWDER_CAT(a, b) POWDER_CAT_(a, b)
#define POWDER_STR_(a) #a
#define POWDER_STR(a) POWDER_STR_(a)

#if defined(POWDER_VARIANT)
NAMESPACE_BEGIN(mitsuba)
namespace powder_variant {
#if defined(POWDER_BACKEND_scalar)
    using F = float;
#elif defined(POWDER_BACKEND_llvm)
    using F = dr::DiffArray<JitBackend::LLVM, float>;
#elif defined(POWDER_BACKEND_cuda)
    using F = dr::DiffArray<JitBackend::CUDA, float>;
#else
#error "POWDER_BACKEND_<scalar|llvm|cuda> is not defined"
#endif
#if POWDER_CHANNELS == 0
    using U = Spectrum<F, 4>;
#else
    using U = Color<F, POWDER_CHANNELS>;
#endif
#if POWDER_POLARIZED
    using S = MuellerMatrix<U>;
#else
    using S = U;
#endif
    constexpr bool same(const char *a, const char *b) {
        return *a == *b && (*a == '\0' || same(a + 1, b + 1));
    }
    static_assert(detail::variant<F, S>::name != nullptr &&
                      same(detail::variant<F, S>::name, POWDER_STR(POWDER_VARIANT)),
                  "the types derived from POWDER_VARIANT do not match the installed "
                  "Mitsuba's variant of that name");
}

void POWDER_CAT(powder_register_, POWDER_VARIANT)(std::string_view name,
                                                   PluginRegisterFn fn) {
    using P = Powder<powder_variant::F, powder_variant::S>;
    fn(name, P::Variant, P::Type,
       [](void *, const Properties &p) -> ref<Object> { return new P(p); });
}
NAMESPACE_END(mitsuba)

#elif defined(POWDER_REGISTRY)
#include "powder_variants.h"
NAMESPACE_BEGIN(mitsuba)
#define POWDER_DECLARE(v) void powder_register_##v(std::string_view, PluginRegisterFn);
POWDER_FOR_EACH_VARIANT(POWDER_DECLARE)
NAMESPACE_END(mitsuba)

extern "C" MI_EXPORT void init_plugin(std::string_view name, mitsuba::PluginRegisterFn fn) {
    using namespace mitsuba;
#define POWDER_REGISTER(v) powder_register_##v(name, fn);
    POWDER_FOR_EACH_VARIANT(POWDER_REGISTER)
}
#else
#error "compile powder.cpp with POWDER_VARIANT=<variant> or POWDER_REGISTRY"
#endif
