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
#include "powder_params.h"
#include "powder_sampling.h"
#include "powder_tables.h"
#include "powder_terms.h"
#include "powder_variant.h"
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
   - Grain radius r in micrometres; an error with ``albedo``; the crystallite radius with
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
   - Volume fraction of the solid of the second population; needs ``radius2``; population 1
     gets 1 - the fractions of the others, which sum to at most 1
     (Default: none (one population), range [0, 1])
   - |exposed|, |differentiable|

 * - radius3, fraction3, radius4, fraction4
   - |float| or |texture|
   - Radius (micrometres) and volume fraction of the solid of a third (``radius3``,
     ``fraction3``) and a fourth (``radius4``, ``fraction4``) grain population; both or neither,
     and the population before (population 2 for the third, 3 for the fourth)
     (Population 3: Default: none (no third population); population 4: Default: none (no fourth
     population); range (0, inf) for the radii, range [0, 1] for the fractions)
   - |exposed|, |differentiable|

 * - material2, material3, material4
   - |string|
   - Grain material of population j = 2..4 (as ``material``), for pigment mixtures; needs
     ``radius{j}`` (Default: the material of population 1)

 * - eta2, k2, eta3, k3, eta4, k4
   - |float| or |spectrum|
   - Optical constants of population j = 2..4 instead of ``material{j}``; both or neither
     (Default: from ``material{j}``, range eta in [0.001, 1000], k in [0, 1000])

 * - agglomerate_radius
   - |float| or |texture|
   - Radius R_a of an agglomerate in micrometres; required with ``grains`` =
     ``agglomerate``, not allowed otherwise (Default: none (required with agglomerates),
     range (0, inf); size parameter 2 pi R_a / lambda in [1e-3, 200])
   - |exposed|, |differentiable|

 * - agglomerate_fill
   - |float| or |texture|
   - Volume fill f of crystallites in an agglomerate, ``grains`` = ``agglomerate`` only
     (Default: 0.5, range [1e-06, 1])
   - |exposed|, |differentiable|

 * - mixing
   - |string|
   - Effective-medium rule of an agglomerate: ``bruggeman`` (Default) or
     ``maxwell_garnett``

 * - material
   - |string|
   - Grain material for Mie theory and tau_o: ``hematite``, ``magnetite``, ``calcite``,
     ``quartz``, ``rutile``, ``kaolinite``, ``gypsum`` or a refractiveindex.info YAML file
     (Default: ``hematite``)

 * - eta, k
   - |float| or |spectrum|
   - Optical constants n and k of the grain material, instead of ``material``; both or
     neither (Default: from ``material``, range eta in [0.001, 1000], k in [0, 1000])

 * - amplitude_volume
   - |float| or |texture|
   - Amplitude A_v of the volume terms (Default: 1.0, range [0, 1e+16])
   - |exposed|, |differentiable|

 * - g
   - |float| or |texture|
   - Henyey-Greenstein anisotropy of a grain (Default: 0.0, range (-1, 1))
   - |exposed|, |differentiable|

 * - extinction
   - |float| or |texture|
   - Extinction coefficient kappa in 1/micrometre (Default: 1.0, range [1e-08, inf))
   - |exposed|, |differentiable|

 * - tau_o
   - |float| or |texture|
   - Extrapolation ratio of the diffusion boundary; exposed only when given
     (Default: from Fresnel of Re(eta), range [0, 1e+20])
   - |exposed|, |differentiable|

 * - thickness
   - |float| or |texture|
   - Layer thickness d in micrometres (Default: infinite, range [0, inf])
   - |exposed|, |differentiable|

 * - amplitude_surface
   - |float| or |texture|
   - Surface amplitude A_s' in micrometre^2 (Harvey-Shack) or A_s (Gaussian)
     (Default: 0.0, range [0, 1e+06])
   - |exposed|, |differentiable|

 * - correlation_length
   - |float| or |texture|
   - Correlation length l_c of the surface in micrometres, Harvey-Shack only
     (Default: 1.0, range (0, 1e+08])
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
     range [1e-18, pi/2])
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
     range [1, 1e+06])

 * - rgb_wavelengths
   - |string|
   - Wavelengths in nm of the R, G, B channels in RGB variants, each in [1, 1e+06]
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
class Powder final : public BSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)
    using Params = PowderParams<Float, Spectrum>;
    using Grains = PowderGrains<Float, Spectrum>;
    using Sampling = PowderSampling<Float, Spectrum>;
    using Tables = PowderTables<Float, Spectrum>;
    using FloatStorage = typename Tables::FloatStorage;
    using UInt64Storage = typename Tables::UInt64Storage;
    using SpecularModel = typename Params::SpecularModel;
    using LobeWeights = typename Sampling::LobeWeights;
    using Lobes = powder_param::Lobes;
    using Volume = PowderVolume<Float, Spectrum>;
    using VolumeConstants = typename Volume::Constants;
    using Energy = PowderEnergy<Float, Spectrum>;

    Powder(const Properties &props) : Base(props), m_params(props), m_grains(m_params) {
        // Components: volume (diffuse), coherent back-scattering and surface (glossy)
        const Lobes &lobes = m_params.lobes;
        if (lobes.single || lobes.multiple) {
            m_comp_volume = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide);
        }
        if (lobes.coherent) {
            m_comp_coherent = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::GlossyReflection | BSDFFlags::FrontSide);
        }
        if (lobes.surface) {
            m_comp_surface = (uint32_t) m_components.size();
            m_components.push_back(BSDFFlags::GlossyReflection | BSDFFlags::FrontSide);
        }
        m_flags = 0;
        for (uint32_t c : m_components)
            m_flags |= c;
        parameters_changed();
        warn_reflects_more_than_received();
    }

    void traverse(TraversalCallback *cb) override {
        const Params &p = m_params;
        for (size_t i = 0; i < powder_param::Count; ++i) {
            if (!p.in_use((powder_param::Id) i))
                continue;
            // (the agglomerate property a grain texture table holds at one value is not)
            bool held = p.agglomerate() && !p.albedo && p.grain_textured() &&
                        (i == powder_param::AgglomerateRadius ||
                         i == powder_param::AgglomerateFill) &&
                        i != (size_t) p.table_param();
            uint32_t flags = (uint32_t) (powder_param::Table[i].fittable && !held
                                             ? ParamFlags::Differentiable
                                             : ParamFlags::NonDifferentiable);
            if (p.textures[i]) // e.g. "g.data" for a bitmap, as Mitsuba's own textures
                cb->put(powder_param::Table[i].name, m_params.textures[i], flags);
            else
                cb->put(powder_param::Table[i].name, m_params[(powder_param::Id) i], flags);
        }
        if (p.albedo)
            cb->put("albedo", m_params.albedo, ParamFlags::Differentiable);
    }

    void parameters_changed(const std::vector<std::string> &keys = {}) override {
        m_params.check(); // edits through mi.traverse() are checked like properties

        // An infinite layer needs no thickness factor (and 0 * inf would
        // poison the gradients of the extinction); a thickness texture is finite.
        // With one thickness per lane, the factor is evaluated when any is finite (it
        // is 1 in the infinite lanes)
        m_finite_thickness =
            m_params.textured(powder_param::Thickness) ||
            std::isfinite(std::get<0>(powder_param::lane_range(m_params.thickness)));

        // Opaque first: the Mie tangents below must not bake the radius in as a literal
        // (that would compile a new kernel for every radius an optimiser tries)
        for (size_t i = 0; i < powder_param::Count; ++i)
            dr::make_opaque(m_params[(powder_param::Id) i]);

        m_grains.update(m_params, keys);

        if (!is_spectral_v<Spectrum> && !m_params.textured(powder_param::Extinction)) {
            m_k0_kappa = dr::TwoPi<ScalarFloat> /
                         (m_params.wavelengths_um(dr::zeros<SurfaceInteraction3f>(1)) *
                          m_params.kappa);
            dr::make_opaque(m_k0_kappa);
        }

        update_volume();

        // Detached means, used only to weight the sampling lobes
        m_sampling.update(m_params, m_grains);

        if (m_params.conserving)
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

        if (unlikely(!lobes.some() || dr::none_or<false>(active)))
            return { bs, 0.f };

        Float lam_mean = m_params.mean_wavelength(si);
        LobeWeights w = m_sampling.lobe_weights(m_params, m_grains, si, lam_mean, lobes);

        Mask pick_coherent = active && (sample1 < w.coherent),
             pick_surface  = active && !pick_coherent &&
                             (sample1 < w.coherent + w.surface),
             pick_diffuse  = active && !pick_coherent && !pick_surface;

        // sample1 picks the lobe, sample2 draws the direction from it
        Vector3f wo = warp::square_to_cosine_hemisphere(sample2);
        if (lobes.coherent)
            dr::masked(wo, pick_coherent) =
                Sampling::sample_coherent(si.wi, w.width_coherent, sample2);
        if (lobes.surface)
            dr::masked(wo, pick_surface) =
                Sampling::sample_surface(m_params, si.wi, w.width_surface, sample2);

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
        if (Lobes lobes = enabled_lobes(ctx); likely(lobes.some())) {
            active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
            UnpolarizedSpectrum value =
                eval_brdf(lobes, si, wo, m_params.wavelengths_um(si), active) *
                Frame3f::cos_theta(wo);
            return depolarizer<Spectrum>(dr::select(active, value, 0.f));
        }
        return 0.f;
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
              const Vector3f &wo, Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFEvaluate, active);
        Lobes lobes = enabled_lobes(ctx);
        if (unlikely(!lobes.some()))
            return 0.f;
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        Float lam_mean = m_params.mean_wavelength(si);
        LobeWeights w = m_sampling.lobe_weights(m_params, m_grains, si, lam_mean, lobes);
        return Sampling::pdf(m_params, lobes, si, wo, w, active);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx,
                                        const SurfaceInteraction3f &si,
                                        const Vector3f &wo,
                                        Mask active) const override {
        MI_MASKED_FUNCTION(ProfilerPhase::BSDFEvaluate, active);
        Lobes lobes = enabled_lobes(ctx);
        if (unlikely(!lobes.some()))
            return { 0.f, 0.f };
        Float lam_mean = m_params.mean_wavelength(si);
        LobeWeights w = m_sampling.lobe_weights(m_params, m_grains, si, lam_mean, lobes);
        auto [value, pdf] = eval_pdf_impl(lobes, si, wo, w, active);
        return { depolarizer<Spectrum>(value), pdf };
    }

    Spectrum eval_diffuse_reflectance(const SurfaceInteraction3f &si,
                                      Mask active) const override {
        return depolarizer<Spectrum>(m_grains.albedo(m_params, si, active));
    }

    /// Attributes: "albedo" (rho), "tau_o", and with the Mie path "q_ext",
    /// "q_sca" (first population) and "q_ext2", "q_sca2" (second)
    Mask has_attribute(const std::string &name, Mask /*active*/) const override {
        bool tables = !m_params.albedo && !m_params.grain_textured();
        return name == "albedo" || name == "tau_o" ||
               (tables && (name == "q_ext" || name == "q_sca")) ||
               (tables && m_params.two_populations && (name == "q_ext2" || name == "q_sca2"));
    }

    UnpolarizedSpectrum eval_attribute(const std::string &name,
                                       const SurfaceInteraction3f &si,
                                       Mask active) const override {
        if (name == "albedo")
            return m_grains.albedo(m_params, si, active);
        if (name == "tau_o")
            return m_grains.tau_o(m_params, si, active);
        if (!dr::any_nested(has_attribute(name, active)))
            Throw("powder: no attribute \"%s\"; available: albedo, tau_o%s", name,
                  m_params.albedo || m_params.grain_textured()
                      ? "" : (m_params.two_populations ? ", q_ext, q_sca, q_ext2, q_sca2"
                                                       : ", q_ext, q_sca"));
        const typename Tables::MieTables &mie = m_grains.mie;
        const FloatStorage &table = name == "q_ext" ? mie.qext
                                  : name == "q_sca" ? mie.qsca
                                  : name == "q_ext2" ? mie.qext2 : mie.qsca2;
        return Tables::lookup(table, si, active);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        const Params &p = m_params;
        auto show = [&](powder_param::Id id) {
            return p.textures[id] ? string::indent(p.textures[id]) : string::indent(p[id]);
        };
        using namespace powder_param;
        oss << "Powder[" << std::endl
            << "  amplitude_volume = " << show(AmplitudeVolume) << "," << std::endl
            << "  g = " << show(G) << "," << std::endl
            << "  extinction = " << show(Extinction) << " [1/um]," << std::endl
            << "  albedo = " << (p.albedo ? string::indent(p.albedo)
                                          : std::string("from the grains")) << "," << std::endl;
        if (!p.albedo)
            oss << "  grains = " << GrainValues[(size_t) p.grain_model] << "," << std::endl;
        oss << "  radius = " << string::indent(p.radius) << " [um]," << std::endl;
        if (!p.albedo && p.agglomerate())
            oss << "  agglomerate_radius = " << string::indent(p.agglomerate_radius)
                << " [um]," << std::endl
                << "  agglomerate_fill = " << string::indent(p.agglomerate_fill) << ","
                << std::endl
                << "  mixing = " << MixingValues[(size_t) p.mixing] << "," << std::endl;
        for (size_t j = 1; j < p.populations; ++j)
            oss << "  " << Table[PopulationRadius[j]].name << " = "
                << string::indent(p[PopulationRadius[j]]) << " [um]," << std::endl
                << "  " << Table[PopulationFraction[j]].name << " = "
                << string::indent(p[PopulationFraction[j]]) << "," << std::endl
                << (p.material_of[j] == 0 ? std::string()
                                          : "  optical constants " + std::to_string(j + 1) +
                                                " = " + p.materials[p.material_of[j]].source +
                                                ",\n");
        oss << "  optical constants = " << p.optics.source << "," << std::endl
            << "  tau_o = " << (p.tau_given ? show(TauO) : std::string("from Fresnel (Re eta)"))
            << "," << std::endl
            << "  thickness = " << show(Thickness) << " [um]," << std::endl
            << "  specular = " << SpecularValues[(size_t) p.specular] << "," << std::endl
            << "  surface_fresnel = " << SurfaceFresnelValues[p.surface_fresnel] << ","
            << std::endl
            << "  amplitude_surface = " << show(AmplitudeSurface) << "," << std::endl;
        if (p.specular == SpecularModel::HarveyShack)
            oss << "  correlation_length = " << show(CorrelationLength) << " [um]," << std::endl;
        else
            oss << "  sigma = " << show(Sigma) << " [rad]," << std::endl;
        oss << "  lobes = \"" << lobes_string(p.lobes) << "\"," << std::endl
            << "  sampling = " << SamplingValues[p.cosine_only] << "," << std::endl
            << "  energy = " << EnergyValues[p.conserving] << "," << std::endl
            << "  volume constants = " << describe(m_volume_path) << "," << std::endl
            << "  wavelength = " << p.wavelength << " [nm] (mono)," << std::endl
            << "  rgb_wavelengths = " << p.rgb_wavelengths[0] << ", "
            << p.rgb_wavelengths[1] << ", " << p.rgb_wavelengths[2] << " [nm] (rgb)" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(Powder)

private:
    Lobes enabled_lobes(const BSDFContext &ctx) const {
        const Lobes &lobes = m_params.lobes;
        bool volume = ctx.is_enabled(BSDFFlags::DiffuseReflection, m_comp_volume);
        Lobes l;
        l.single = lobes.single && volume;
        l.multiple = lobes.multiple && volume;
        l.coherent = lobes.coherent && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_coherent);
        l.surface = lobes.surface && ctx.is_enabled(BSDFFlags::GlossyReflection, m_comp_surface);
        return l;
    }

    /**
     * energy = "paper": warn when the ladder terms reflect more than the light they receive
     * at normal incidence (powder::ladder_reflectance_normal) at a wavelength of the grain
     * tables, e.g. a white powder with the Fresnel tau_o of its material (docs/powder.md,
     * "Energy"); textured parameters at their largest values (g: both ends), an albedo from
     * spatially varying grains at its mean
     */
    void warn_reflects_more_than_received() const {
        using namespace powder_param;
        const Params &p = m_params;
        if (p.conserving || !(p.lobes.single || p.lobes.multiple))
            return;
        auto largest = [&](Id id) {
            return p.textured(id) ? p.texture_values(id).hi : Params::value_of(p[id]);
        };
        size_t n = m_grains.table_wavelengths.size();
        std::vector<ScalarFloat> rho(n, (ScalarFloat) m_grains.grain_rho_mean),
            tau = p.tau_given ? std::vector<ScalarFloat>(n, (ScalarFloat) largest(TauO))
                              : Tables::download(m_grains.tau_table);
        if (p.albedo && p.albedo->is_spatially_varying()) {
            ScalarFloat max_value = 1.f;
            try {
                max_value = p.albedo->max();
            } catch (const std::exception &) {
                // this texture type cannot report its maximum: at most 1
            }
            rho.assign(n, max_value);
        } else if (p.albedo)
            rho = PowderTextures<Float, Spectrum>::grid_values(p.albedo.get());
        else if (!p.grain_textured())
            rho = Tables::download(m_grains.mie.rho);
        std::vector<double> gs{ Params::value_of(p.g) };
        if (p.textured(G))
            gs = { p.texture_values(G).lo, p.texture_values(G).hi };
        double d = p.textured(Thickness) ? Inf : Params::value_of(p.thickness),
               worst = 0.0;
        size_t at = 0;
        for (size_t i = 0; i < n; ++i)
            for (double g : gs) {
                double r = powder::ladder_reflectance_normal(
                    rho[i], g, tau[i], largest(AmplitudeVolume), largest(Extinction), d,
                    p.lobes.single, p.lobes.multiple);
                if (r > worst) {
                    worst = r;
                    at = i;
                }
            }
        if (worst > 1.0)
            Log(Warn,
                "powder: this powder reflects %.4g times the light it receives at normal "
                "incidence (energy = \"paper\": the ladder terms L1 + L2 at %g nm, albedo "
                "%g, tau_o %g): more than it receives, which no powder does; the extrapolation "
                "ratio tau_o of the diffusion approximation makes a bright powder brighter "
                "than white (see docs/powder.md, \"Energy\"). Use energy = \"conserving\" "
                "(at most 1), or a smaller albedo, tau_o or amplitude_volume",
                worst, m_grains.table_wavelengths[at], (double) rho[at], (double) tau[at]);
    }

    // ---------------------------------------------------- volume constants

    /// Spectral variants, an albedo that is one number and tau_o from the Fresnel table:
    /// whether the layer is optically thick at every wavelength (powder_volume.h, ThickLimit)
    bool optically_thick() const {
        Float rho = m_params.albedo->eval(dr::zeros<SurfaceInteraction3f>(1), true)[0],
              c0 = dr::sqrt(powder::c0_squared(rho, m_params.g));
        double x0 = std::get<0>(powder_param::lane_range(
            2.f * dr::detach(c0) * dr::min(dr::detach(m_grains.tau_table))));
        return x0 * (1.0 - powder::SaturationMargin) >= ThickLimit;
    }

    /// How eval obtains the volume constants (VolumePath), the constants or their table,
    /// and the form of C for the smallest x0 = 2 c0 tau_o they allow
    void update_volume() {
        const Params &p = m_params;
        // The same for every interaction when the albedo and tau_o are (spectral: when the
        // albedo is one number for every wavelength and so is tau_o: given, or from a
        // constant index; or the layer is optically thick)
        bool same = (!p.albedo || !p.albedo->is_spatially_varying()) &&
                    !p.textured(powder_param::G) && !p.textured(powder_param::TauO) &&
                    !p.grain_textured(),
             thick_layer = false;
        if constexpr (is_spectral_v<Spectrum>) {
            same &= p.uniform_spectrum_albedo();
            if (same && !p.tau_given && !m_grains.tau_table_constant)
                same = thick_layer = optically_thick();
        }
        m_volume_path = VolumePath::PerLane;
        double x0 = 0.0;
        if (same) {
            m_volume_path = thick_layer ? VolumePath::UniformThick : VolumePath::Uniform;
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(1);
            // optically thick: s(c0) = 1 / (2 c0), and tau_o, which neither L2 nor C then
            // reads, is set to its smallest value (x0 below)
            m_volume = Volume::constants(
                m_grains.albedo(p, si, true),
                thick_layer ? UnpolarizedSpectrum(dr::min(m_grains.tau_table))
                            : m_grains.tau_o(p, si, true),
                p.g);
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
        if (!tabulated(m_volume_path)) { // no stale table (nor its AD graph) kept
            m_volume_table = FloatStorage();
            m_volume_pairs = UInt64Storage();
        }
        m_coherent_form = powder::coherent_form(x0, thick(m_volume_path));
    }

    /// Spectral variants: the table of the volume constants on the 1 nm grid when they
    /// depend on the wavelength only (Volume::build_table); its lower bound of x0
    VolumePath volume_table(double &x0) {
        const Params &p = m_params;
        if (p.grain_textured() || p.textured(powder_param::G) ||
            p.textured(powder_param::TauO) || dr::width(p.g) != 1 ||
            (p.tau_given && dr::width(p.tau_o) != 1) ||
            (p.albedo && !p.uniform_spectrum_albedo()))
            return VolumePath::PerLane;
        Float rho_value = p.albedo ? Float(p.albedo->eval(dr::zeros<SurfaceInteraction3f>(1),
                                                           true)[0])
                                   : Float(0.f);
        if (dr::width(rho_value) != 1)
            return VolumePath::PerLane;
        FloatStorage rho = p.albedo ? Volume::broadcast(rho_value, Tables::TableSize)
                                    : m_grains.mie.rho,
                     tau = p.tau_given ? Volume::broadcast(p.tau_o, Tables::TableSize)
                                       : m_grains.tau_table;
        return Volume::build_table(rho, p.albedo ? &rho_value : nullptr, tau, p.g, m_volume,
                                   m_volume_table, m_volume_pairs, x0);
    }

    /// The volume constants at an interaction (VolumePath)
    VolumeConstants volume_constants(const SurfaceInteraction3f &si, Mask active) const {
        if (uniform(m_volume_path))
            return m_volume;
        if constexpr (is_spectral_v<Spectrum>)
            if (tabulated(m_volume_path))
                return Volume::lookup(m_volume_table, m_volume_pairs, m_volume_path, m_volume,
                                      m_params.g, si, active);
        Float g = m_params.at(powder_param::G, si, active);
        if constexpr (is_spectral_v<Spectrum>) {
            if (!m_params.albedo && !m_params.tau_given &&
                !m_params.grain_textured()) { // one packet gather
                auto [rho, tau] = m_grains.lookup(si, active);
                return Volume::constants(rho, tau, g);
            }
        }
        return Volume::constants(m_grains.albedo(m_params, si, active),
                                 m_grains.tau_o(m_params, si, active), g);
    }

    /// energy = "conserving": tabulate N (powder_energy.h) for the configured volume lobes
    void update_energy_norm() {
        if (!m_params.lobes.volume())
            return; // no volume term: eval never reads the table
        Lobes lobes = m_params.lobes;
        lobes.surface = false;
        auto terms = [&](const SurfaceInteraction3f &si, const Vector3f &wi, const Vector3f &wo) {
            VolumeConstants k = volume_constants(si, Mask(true));
            return volume_terms(lobes, si, wi, wo, k,
                                k0_over_kappa(m_params.inverse_wavelengths_um(si), si, true),
                                true);
        };
        m_norm_records = Energy::records(Energy::table(terms, m_params.av));
    }

    // ---------------------------------------------------------- the model

    /// k0 / kappa = 2 pi / (lambda kappa) per channel (lambda in um), docs/model.md Eq. 10;
    /// precomputed in RGB and mono variants, where lambda is fixed, unless the extinction
    /// is a texture (inv_lam: 1 / lambda per channel, shared with the surface term)
    UnpolarizedSpectrum k0_over_kappa(const UnpolarizedSpectrum &inv_lam,
                                      const SurfaceInteraction3f &si, Mask active) const {
        if (is_spectral_v<Spectrum> || m_params.textured(powder_param::Extinction))
            return inv_lam *
                   (dr::TwoPi<ScalarFloat> / m_params.at(powder_param::Extinction, si, active));
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
            Float factor = powder::single_scattering(m_params.at(powder_param::G, si, active),
                                                     wi, wo, mu_sum);
            if (m_finite_thickness)
                factor *= powder::thickness_factor(
                    m_params.at(powder_param::Extinction, si, active),
                    m_params.at(powder_param::Thickness, si, active), mu_i, mu_o);
            ladder += k.rho * factor;
        }
        if (lobes.multiple) // L2 (optically thick: s(c0) = 1 / (2 c0), one division)
            ladder += thick(m_volume_path)
                          ? powder::multiple_scattering_thick(k.rho2_3, k.c0, h, mu_i, mu_o)
                          : powder::multiple_scattering(k.rho2_3, k.s_c0, k.c0, h, mu_i, mu_o);
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
            inv_lam = m_params.inverse_wavelengths_um(si); // 1 / lambda (1/um), for k0 / kappa and S

        if (lobes.volume()) {
            VolumeConstants k = volume_constants(si, active);
            auto [ladder, coherent] = volume_terms(lobes, si, wi, wo, k,
                                                   k0_over_kappa(inv_lam, si, active), active);
            UnpolarizedSpectrum volume = ladder + coherent; // L1 + L2 + C
            if (m_params.conserving) // energy = "conserving": times N(mu_i), per channel
                volume *= Energy::lookup(m_norm_records, mu_i, lam, active);
            result = volume * (m_params.at(powder_param::AmplitudeVolume, si, active) *
                               dr::InvFourPi<ScalarFloat>);
        }

        if (lobes.surface) {
            UnpolarizedSpectrum S;
            Float as = m_params.at(powder_param::AmplitudeSurface, si, active);
            if (m_params.specular == SpecularModel::HarveyShack)
                S = powder::surface_harvey_shack(
                    as, m_params.at(powder_param::CorrelationLength, si, active), wi, wo,
                    mu_sum, inv_lam);
            else
                S = powder::surface_gaussian(as, m_params.at(powder_param::Sigma, si, active),
                                             mirror_angle(wi, wo));
            if (m_params.surface_fresnel) // surface_fresnel: S F(c) / F(1), c = wi . h
                S *= Tables::fresnel_factor(m_grains.fresnel, si,
                                            powder::half_vector_cosine(dr::dot(wi, wo)), active);
            result += S;
        }
        return result;
    }

    /// Angle between wo and the mirror direction of wi (stable near 0)
    static Float mirror_angle(const Vector3f &wi, const Vector3f &wo) {
        return powder::angle_between(wo, Vector3f(-wi.x(), -wi.y(), wi.z()));
    }

    std::pair<UnpolarizedSpectrum, Float>
    eval_pdf_impl(const Lobes &lobes, const SurfaceInteraction3f &si, const Vector3f &wo,
                  const LobeWeights &w, Mask active) const {
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        UnpolarizedSpectrum value =
            eval_brdf(lobes, si, wo, m_params.wavelengths_um(si), active) *
            Frame3f::cos_theta(wo);
        Float pdf = Sampling::pdf(m_params, lobes, si, wo, w, active);
        return { dr::select(active, value, 0.f), pdf };
    }

    // -------------------------------------------------------------- state

    Params m_params;     ///< the properties (powder_params.h)
    Grains m_grains;     ///< the grain tables (powder_grains.h)
    Sampling m_sampling; ///< what the sampling weights read (powder_sampling.h)
    uint32_t m_comp_volume = 0, m_comp_coherent = 0, m_comp_surface = 0;
    // what eval reads (parameters_changed)
    bool m_finite_thickness = false;
    UnpolarizedSpectrum m_k0_kappa = 0.f; ///< RGB and mono: k0 / kappa per channel
    VolumePath m_volume_path = VolumePath::PerLane;
    powder::CoherentForm m_coherent_form = powder::CoherentForm::WithSeries;
    VolumeConstants m_volume;      ///< the constants eval does not read from a table
    FloatStorage m_volume_table;   ///< spectral: records of the volume constants
    UInt64Storage m_volume_pairs;  ///< JIT spectral, records of rho alone: packed_pairs
    FloatStorage m_norm_records;   ///< energy = "conserving": N (powder_energy.h)

    MI_TRAVERSE_CB(Base, m_params, m_grains, m_sampling, m_k0_kappa, m_volume, m_volume_table,
                   m_volume_pairs,
                   m_norm_records)
};

POWDER_EXPORT_VARIANT(Powder)

NAMESPACE_END(mitsuba)
