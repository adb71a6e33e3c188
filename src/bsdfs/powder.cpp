#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>
#include <mitsuba/core/string.h>
#include <mitsuba/core/frame.h>
#include <mitsuba/core/warp.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/texture.h>

#include <array>
#include <cmath>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "powder_energy.h"
#include "powder_grains.h"
#include "powder_lobes.h"
#include "powder_terms.h"
#include "powder_volume.h"

NAMESPACE_BEGIN(mitsuba)

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
``powder_param::Table`` (powder_registry.h; tests/plugin/test_params_doc.py compares the two). Those
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
class Powder final : public BSDF<Float, Spectrum>, public PowderGrains<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)
    using Grains = PowderGrains<Float, Spectrum>;
    using typename Grains::Tables;
    using typename Grains::FloatStorage;
    using typename Grains::SpecularModel;
    using Lobes = powder_param::Lobes;
    using Volume = PowderVolume<Float, Spectrum>;
    using VolumeConstants = typename Volume::Constants;
    using Energy = PowderEnergy<Float, Spectrum>;
    using Grains::TableSize;
    // the properties (powder_params.h) and the grains (powder_grains.h)
    using Grains::m_albedo, Grains::m_av, Grains::m_g, Grains::m_kappa, Grains::m_tau_o,
        Grains::m_thickness, Grains::m_radius, Grains::m_radius2, Grains::m_fraction2,
        Grains::m_agglomerate_radius, Grains::m_agglomerate_fill, Grains::m_textures,
        Grains::m_grain_model, Grains::m_mixing, Grains::m_tau_given, Grains::m_two_populations,
        Grains::m_specular, Grains::m_surface_fresnel, Grains::m_cosine_only,
        Grains::m_conserving, Grains::m_lobes, Grains::m_wavelength, Grains::m_rgb_wavelengths,
        Grains::m_optics, Grains::m_mie, Grains::m_tau_table, Grains::m_tau_table_constant,
        Grains::m_packed, Grains::m_rho_channels, Grains::m_tau_channels, Grains::m_fresnel,
        Grains::m_grain, Grains::m_grain_rho_mean, Grains::m_lc, Grains::m_sigma, Grains::m_as;
    using Grains::at, Grains::textured, Grains::in_use, Grains::member, Grains::agglomerate,
        Grains::grain_textured, Grains::table_param, Grains::uniform_spectrum_albedo,
        Grains::wavelengths_um, Grains::inverse_wavelengths_um, Grains::mean_wavelength,
        Grains::albedo, Grains::tau_o, Grains::lookup_grains, Grains::read_properties,
        Grains::warn_outside_regime, Grains::read_grain_index, Grains::check_parameters,
        Grains::update_grains;

    Powder(const Properties &props) : Base(props) {
        read_properties(props);
        warn_outside_regime();
        read_grain_index();
        // Components: volume (diffuse), coherent back-scattering and surface (glossy)
        if (m_lobes.single || m_lobes.multiple) {
            m_comp_volume = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide);
        }
        if (m_lobes.coherent) {
            m_comp_coherent = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::GlossyReflection | BSDFFlags::FrontSide);
        }
        if (m_lobes.surface) {
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
            if (!in_use((powder_param::Id) i))
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
        check_parameters(); // edits through mi.traverse() are checked like properties

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

        update_grains(keys);

        if (!is_spectral_v<Spectrum> && !textured(powder_param::Extinction)) {
            m_k0_kappa = dr::TwoPi<ScalarFloat> /
                         (wavelengths_um(dr::zeros<SurfaceInteraction3f>(1)) * m_kappa);
            dr::make_opaque(m_k0_kappa);
        }

        update_volume();

        // Detached means, used only to weight the sampling lobes
        m_rho_mean = m_albedo ? dr::detach(m_albedo->mean())
                              : grain_textured() ? Float((ScalarFloat) m_grain_rho_mean)
                              : Float(dr::mean(dr::detach(m_mie.rho)));
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
        if (Lobes lobes = enabled_lobes(ctx); likely(lobes.any())) {
            active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
            UnpolarizedSpectrum value =
                eval_brdf(lobes, si, wo, wavelengths_um(si), active) * Frame3f::cos_theta(wo);
            return depolarizer<Spectrum>(dr::select(active, value, 0.f));
        }
        return 0.f;
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
        const FloatStorage &table = name == "q_ext" ? m_mie.qext
                                  : name == "q_sca" ? m_mie.qsca
                                  : name == "q_ext2" ? m_mie.qext2 : m_mie.qsca2;
        return Tables::lookup(table, si, active);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        auto show = [&](powder_param::Id p) {
            return m_textures[p] ? string::indent(m_textures[p])
                                 : string::indent(this->*member(p));
        };
        using namespace powder_param;
        oss << "Powder[" << std::endl
            << "  amplitude_volume = " << show(AmplitudeVolume) << "," << std::endl
            << "  g = " << show(G) << "," << std::endl
            << "  extinction = " << show(Extinction) << " [1/um]," << std::endl
            << "  albedo = " << (m_albedo ? string::indent(m_albedo)
                                          : std::string("from the grains")) << "," << std::endl;
        if (!m_albedo)
            oss << "  grains = " << GrainValues[(size_t) m_grain_model] << "," << std::endl;
        oss << "  radius = " << string::indent(m_radius) << " [um]," << std::endl;
        if (!m_albedo && agglomerate())
            oss << "  agglomerate_radius = " << string::indent(m_agglomerate_radius)
                << " [um]," << std::endl
                << "  agglomerate_fill = " << string::indent(m_agglomerate_fill) << ","
                << std::endl
                << "  mixing = " << MixingValues[(size_t) m_mixing] << "," << std::endl;
        if (m_two_populations)
            oss << "  radius2 = " << string::indent(m_radius2) << " [um]," << std::endl
                << "  fraction2 = " << string::indent(m_fraction2) << "," << std::endl;
        oss << "  optical constants = " << m_optics.source << "," << std::endl
            << "  tau_o = " << (m_tau_given ? show(TauO) : std::string("from Fresnel (Re eta)"))
            << "," << std::endl
            << "  thickness = " << show(Thickness) << " [um]," << std::endl
            << "  specular = " << SpecularValues[(size_t) m_specular] << "," << std::endl
            << "  surface_fresnel = " << SurfaceFresnelValues[m_surface_fresnel] << ","
            << std::endl
            << "  amplitude_surface = " << show(AmplitudeSurface) << "," << std::endl;
        if (m_specular == SpecularModel::HarveyShack)
            oss << "  correlation_length = " << show(CorrelationLength) << " [um]," << std::endl;
        else
            oss << "  sigma = " << show(Sigma) << " [rad]," << std::endl;
        oss << "  lobes = \"" << lobes_string(m_lobes) << "\"," << std::endl
            << "  sampling = " << SamplingValues[m_cosine_only] << "," << std::endl
            << "  energy = " << EnergyValues[m_conserving] << "," << std::endl
            << "  volume constants = " << describe(m_volume_path) << "," << std::endl
            << "  wavelength = " << m_wavelength << " [nm] (mono)," << std::endl
            << "  rgb_wavelengths = " << m_rgb_wavelengths[0] << ", "
            << m_rgb_wavelengths[1] << ", " << m_rgb_wavelengths[2] << " [nm] (rgb)" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(Powder)

private:
    /// Probabilities of the coherent and surface sampling lobes (the cosine
    /// lobe gets the rest, at least 0.1) and their widths
    struct LobeWeights {
        Float coherent, surface;
        Float width_coherent; ///< scale of the projected 2D Cauchy lobe
        Float width_surface;  ///< std. dev. (projected plane or radians)
    };

    Lobes enabled_lobes(const BSDFContext &ctx) const {
        bool volume = ctx.is_enabled(BSDFFlags::DiffuseReflection, m_comp_volume);
        Lobes l;
        l.single = m_lobes.single && volume;
        l.multiple = m_lobes.multiple && volume;
        l.coherent = m_lobes.coherent && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_coherent);
        l.surface = m_lobes.surface && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_surface);
        return l;
    }

    // ---------------------------------------------------- volume constants

    /// Spectral variants, an albedo that is one number and tau_o from the Fresnel table:
    /// whether the layer is optically thick at every wavelength (powder_volume.h, ThickLimit)
    bool optically_thick() const {
        Float rho = m_albedo->eval(dr::zeros<SurfaceInteraction3f>(1), true)[0],
              c0 = dr::sqrt(powder::c0_squared(rho, m_g));
        double x0 = std::get<0>(powder_param::lane_range(
            2.f * dr::detach(c0) * dr::min(dr::detach(m_tau_table))));
        return x0 * (1.0 - powder::SaturationMargin) >= ThickLimit;
    }

    /// How eval obtains the volume constants (VolumePath), the constants or their table,
    /// and the form of C for the smallest x0 = 2 c0 tau_o they allow
    void update_volume() {
        // The same for every interaction when the albedo and tau_o are (spectral: when the
        // albedo is one number for every wavelength and so is tau_o: given, or from a
        // constant index; or the layer is optically thick)
        bool same = (!m_albedo || !m_albedo->is_spatially_varying()) &&
                    !textured(powder_param::G) && !textured(powder_param::TauO) &&
                    !grain_textured(),
             thick_layer = false;
        if constexpr (is_spectral_v<Spectrum>) {
            same &= uniform_spectrum_albedo();
            if (same && !m_tau_given && !m_tau_table_constant)
                same = thick_layer = optically_thick();
        }
        m_volume_path = VolumePath::PerLane;
        double x0 = 0.0;
        if (same) {
            m_volume_path = thick_layer ? VolumePath::UniformThick : VolumePath::Uniform;
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(1);
            // optically thick: s(c0) = 1 / (2 c0), and tau_o, which neither L2 nor C then
            // reads, is set to its smallest value (x0 below)
            m_volume = Volume::constants(albedo(si, true),
                                         thick_layer ? UnpolarizedSpectrum(dr::min(m_tau_table))
                                                     : tau_o(si, true),
                                         m_g);
            if (thick_layer)
                m_volume.s_c0 = .5f / m_volume.c0;
            dr::make_opaque(m_volume.rho, m_volume.rho2_3, m_volume.c0_sq, m_volume.c0,
                            m_volume.s_c0, m_volume.tau);
            x0 = powder_param::Inf;
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                x0 = std::min(x0, std::get<0>(powder_param::lane_range(
                                      2.f * dr::detach(m_volume.c0[c]) *
                                      dr::detach(m_volume.tau[c]))));
        } else if constexpr (is_spectral_v<Spectrum>) {
            m_volume_path = volume_table(x0);
        }
        if (!tabulated(m_volume_path))
            m_volume_table = FloatStorage(); // no stale table (nor its AD graph) kept
        m_coherent_form = powder::coherent_form(x0, thick(m_volume_path));
    }

    /// Spectral variants: the table of the volume constants on the 1 nm grid when they
    /// depend on the wavelength only (Volume::build_table); its lower bound of x0
    VolumePath volume_table(double &x0) {
        if (grain_textured() || textured(powder_param::G) || textured(powder_param::TauO) ||
            dr::width(m_g) != 1 || (m_tau_given && dr::width(m_tau_o) != 1) ||
            (m_albedo && !uniform_spectrum_albedo()))
            return VolumePath::PerLane;
        Float rho_value = m_albedo ? Float(m_albedo->eval(dr::zeros<SurfaceInteraction3f>(1),
                                                           true)[0])
                                   : Float(0.f);
        if (dr::width(rho_value) != 1)
            return VolumePath::PerLane;
        FloatStorage rho = m_albedo ? Volume::broadcast(rho_value, TableSize) : m_mie.rho,
                     tau = m_tau_given ? Volume::broadcast(m_tau_o, TableSize) : m_tau_table;
        return Volume::build_table(rho, m_albedo ? &rho_value : nullptr, tau, m_g, m_volume,
                                   m_volume_table, x0);
    }

    /// The volume constants at an interaction (VolumePath)
    VolumeConstants volume_constants(const SurfaceInteraction3f &si, Mask active) const {
        if (uniform(m_volume_path))
            return m_volume;
        if constexpr (is_spectral_v<Spectrum>)
            if (tabulated(m_volume_path))
                return Volume::lookup(m_volume_table, m_volume_path, m_volume, m_g, si, active);
        Float g = at(powder_param::G, si, active);
        if constexpr (is_spectral_v<Spectrum>) {
            if (!m_albedo && !m_tau_given && !grain_textured()) { // one packet gather
                auto [rho, tau] = lookup_grains(si, active);
                return Volume::constants(rho, tau, g);
            }
        }
        return Volume::constants(albedo(si, active), tau_o(si, active), g);
    }

    /// energy = "conserving": tabulate N (powder_energy.h) for the configured volume lobes
    void update_energy_norm() {
        if (!m_lobes.volume())
            return; // no volume term: eval never reads the table
        Lobes lobes = m_lobes;
        lobes.surface = false;
        auto terms = [&](const SurfaceInteraction3f &si, const Vector3f &wi, const Vector3f &wo) {
            VolumeConstants k = volume_constants(si, Mask(true));
            return volume_terms(lobes, si, wi, wo, k,
                                k0_over_kappa(inverse_wavelengths_um(si), si, true), true);
        };
        m_norm_records = Energy::records(Energy::table(terms, m_av));
    }

    // ---------------------------------------------------------- the model

    /// k0 / kappa = 2 pi / (lambda kappa) per channel (lambda in um), docs/model.md Eq. 10;
    /// precomputed in RGB and mono variants, where lambda is fixed, unless the extinction
    /// is a texture (inv_lam: 1 / lambda per channel, shared with the surface term)
    UnpolarizedSpectrum k0_over_kappa(const UnpolarizedSpectrum &inv_lam,
                                      const SurfaceInteraction3f &si, Mask active) const {
        if (is_spectral_v<Spectrum> || textured(powder_param::Extinction))
            return inv_lam * (dr::TwoPi<ScalarFloat> / at(powder_param::Extinction, si, active));
        return m_k0_kappa;
    }

    /**
     * The volume terms of docs/model.md Eq. 9 (without A_v / (4 pi)) for the enabled lobes:
     * (L1 + L2, C), the ladder and the cyclical (coherent) term, at the directions wi, wo
     * (mu_i, mu_o > 0), with the volume constants k and k0 / kappa per channel; g,
     * kappa and d of the interaction si (powder_terms.h).
     */
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    volume_terms(const Lobes &lobes, const SurfaceInteraction3f &si, const Vector3f &wi,
                 const Vector3f &wo, const VolumeConstants &k,
                 const UnpolarizedSpectrum &k0_kappa, Mask active) const {
        Float mu_i = Frame3f::cos_theta(wi), mu_o = Frame3f::cos_theta(wo),
              mu_sum = mu_i + mu_o,
              h = mu_i * mu_o / mu_sum; // = 1 / (2 v), docs/model.md Eq. 10b
        UnpolarizedSpectrum ladder(0.f), coherent(0.f);
        if (lobes.single) { // L1
            Float factor = powder::single_scattering(at(powder_param::G, si, active), wi, wo,
                                                     mu_sum);
            if (m_finite_thickness)
                factor *= powder::thickness_factor(at(powder_param::Extinction, si, active),
                                                   at(powder_param::Thickness, si, active),
                                                   mu_i, mu_o);
            ladder += k.rho * factor;
        }
        if (lobes.multiple) // L2
            ladder += powder::multiple_scattering(k.rho2_3, k.s_c0, k.c0, h, mu_i, mu_o);
        if (lobes.coherent) // C
            coherent = powder::coherent(k.rho2_3, k.c0_sq, k.tau, k0_kappa, wi, wo, mu_i, mu_o,
                                        h, m_coherent_form);
        return { ladder, coherent };
    }

    /**
     * The BRDF (without the cosine factor) of docs/model.md, Eq. 23, for the enabled
     * lobes: f = A_v (L1 + L2 + C) / (4 pi) + S. Outside `active`, the cosines
     * mu_i and mu_o are replaced by 1, so that no lane divides by 0 (every term is
     * finite for finite x and y components); the values of those lanes are
     * meaningless, and the callers (eval, eval_pdf_impl) set them to 0 after the
     * cosine factor, which also keeps them out of every gradient
     * (tests/plugin/test_autodiff.py). Only the cosines: a select of the x and y components
     * with the mask compiles to masked loads, which wait for the cosines' loads and
     * the comparison, a cost on batches beyond the caches.
     */
    UnpolarizedSpectrum eval_brdf(const Lobes &lobes, const SurfaceInteraction3f &si,
                                  const Vector3f &wo_, const UnpolarizedSpectrum &lam,
                                  Mask active) const {
        Vector3f wi(si.wi.x(), si.wi.y(), dr::select(active, si.wi.z(), 1.f)),
                 wo(wo_.x(), wo_.y(), dr::select(active, wo_.z(), 1.f));
        Float mu_i = Frame3f::cos_theta(wi), mu_sum = mu_i + Frame3f::cos_theta(wo);

        UnpolarizedSpectrum result(0.f),
            inv_lam = inverse_wavelengths_um(si); // 1 / lambda (1/um), for k0 / kappa and S

        if (lobes.volume()) {
            VolumeConstants k = volume_constants(si, active);
            auto [ladder, coherent] = volume_terms(lobes, si, wi, wo, k,
                                                   k0_over_kappa(inv_lam, si, active), active);
            UnpolarizedSpectrum volume = ladder + coherent; // L1 + L2 + C
            if (m_conserving) // energy = "conserving": times N(mu_i), per channel
                volume *= Energy::lookup(m_norm_records, mu_i, lam, active);
            result = volume * (at(powder_param::AmplitudeVolume, si, active) *
                               dr::InvFourPi<ScalarFloat>);
        }

        if (lobes.surface) {
            UnpolarizedSpectrum S;
            Float as = at(powder_param::AmplitudeSurface, si, active);
            if (m_specular == SpecularModel::HarveyShack)
                S = powder::surface_harvey_shack(
                    as, at(powder_param::CorrelationLength, si, active), wi, wo, mu_sum, inv_lam);
            else
                S = powder::surface_gaussian(as, at(powder_param::Sigma, si, active),
                                             mirror_angle(wi, wo));
            if (m_surface_fresnel) // surface_fresnel: S F(c) / F(1), c = wi . h
                S *= Tables::fresnel_factor(m_fresnel, si,
                                            powder::half_vector_cosine(dr::dot(wi, wo)), active);
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
        Float c0 = dr::sqrt(powder::c0_squared(rho, g));
        Float s0 = powder::s_func(c0, tau);
        Float e_diffuse = 0.f, e_coherent = 0.f;
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
        auto [e_surface, width_s, wide] = surface_estimate(si, lam_mean, mu, as, lobes);

        Float total = e_diffuse + e_coherent + e_surface;
        Mask positive = total > 0.f;
        Float inv_total = dr::select(positive, dr::rcp(total), 0.f);
        LobeWeights w;
        // Probabilities in proportion to the estimated energies, no floors: a lobe with
        // little energy gets few samples (floors make the weights bimodal, and a
        // near-Lambertian powder under broad light noisier than with cosine sampling).
        // The cosine lobe keeps at least 10 %, but for the surface term alone: S is
        // exactly 0 beyond ~9 widths of its lobe (exp2_neg's cut), so cosine samples
        // there would have weight 0, and nothing else is left to sample.
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

    /// The surface lobe's estimated directional albedo, its width and the share of its
    /// probability that goes to the cosine lobe
    std::tuple<Float, Float, Float> surface_estimate(const SurfaceInteraction3f &si,
                                                     const Float &lam_mean, const Float &mu,
                                                     const Float &as, const Lobes &lobes) const {
        Float e_surface = 0.f, width_s, wide = 0.f;
        if (m_specular == SpecularModel::HarveyShack) {
            width_s = lam_mean * dr::InvPi<ScalarFloat> * dr::InvSqrtTwo<ScalarFloat> /
                      dr::detach(at(powder_param::CorrelationLength, si, true));
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
            width_s = dr::detach(at(powder_param::Sigma, si, true));
            if (lobes.surface)
                e_surface = as * width_s * dr::SqrtTwoPi<ScalarFloat> * mu;
        }
        // surface_fresnel: the lobe's energy follows the factor F(mu_i) / F(1) of the
        // mirror direction (channel mean), so that its share of the samples grows with it
        // towards grazing light
        if (lobes.surface && m_surface_fresnel) {
            UnpolarizedSpectrum f = dr::detach(Tables::fresnel_factor(m_fresnel, si, mu, true));
            Float mean = 0.f;
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                mean += f[c];
            e_surface *= mean * (1.f / (ScalarFloat) dr::size_v<UnpolarizedSpectrum>);
        }
        return { e_surface, width_s, wide };
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

    // -------------------------------------------------------------- state

    uint32_t m_comp_volume = 0, m_comp_coherent = 0, m_comp_surface = 0;
    // what eval reads (parameters_changed)
    bool m_finite_thickness = false;
    UnpolarizedSpectrum m_k0_kappa = 0.f; ///< RGB and mono: k0 / kappa per channel
    VolumePath m_volume_path = VolumePath::PerLane;
    powder::CoherentForm m_coherent_form = powder::CoherentForm::WithSeries;
    VolumeConstants m_volume;      ///< the constants eval does not read from a table
    FloatStorage m_volume_table;   ///< spectral: records of the volume constants
    FloatStorage m_norm_records;   ///< energy = "conserving": N (powder_energy.h)
    Float m_rho_mean, m_tau_mean;  ///< detached means for the sampling weights

    MI_TRAVERSE_CB(Base, m_albedo, m_textures, m_av, m_g, m_kappa, m_tau_o, m_thickness, m_as,
                   m_lc, m_sigma, m_radius, m_radius2, m_fraction2, m_agglomerate_radius,
                   m_agglomerate_fill, m_rho_mean, m_tau_mean, m_rho_channels, m_tau_channels,
                   m_k0_kappa, m_packed, m_volume, m_volume_table, m_mie, m_tau_table,
                   m_norm_records,
                   m_fresnel.records, m_grain.records)
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
