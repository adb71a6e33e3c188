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
#include "powder_lobes.h"
#include "powder_params.h"
#include "powder_tables.h"
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
``powder_param::Table`` (powder_registry.h; tests/test_params_doc.py compares the two). Those
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
    using Tables = PowderTables<Float, Spectrum>;
    using Volume = PowderVolume<Float, Spectrum>;
    using VolumeConstants = typename Volume::Constants;
    using Energy = PowderEnergy<Float, Spectrum>;
    using Textures = PowderTextures<Float, Spectrum>;
    using FloatStorage = typename Tables::FloatStorage;
    using Lobes = powder_param::Lobes;
    static constexpr int TableSize = Tables::TableSize;
    static constexpr float TableMin = Tables::TableMin, TableStep = Tables::TableStep;

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

    // ---------------------------------------------------------- properties

    /// Read and check the properties (powder_params.h, the tables of powder_registry.h)
    void read_properties(const Properties &props) {
        using namespace powder_param;
        m_tau_given = props.has_property("tau_o");
        m_two_populations = props.has_property("radius2") || props.has_property("fraction2");
        std::tie(m_grain_model, m_mixing) = read_grain_model(props);
        // The float parameters; a fittable one may be a texture (evaluated at si.uv)
        for (size_t i = 0; i < Count; ++i) {
            const Spec &spec = Table[i];
            double value = spec.def;
            if (props.has_property(spec.name)) {
                auto type = props.type(spec.name);
                if (spec.fittable && (type == Properties::Type::Object ||
                                      type == Properties::Type::Reference ||
                                      type == Properties::Type::ResolvedReference)) {
                    m_textures[i] = props.get_texture<Texture>(spec.name);
                    Textures::check((Id) i, m_textures[i].get());
                } else {
                    value = props.get<double>(spec.name);
                    check_range(spec.name, value, spec.range);
                }
            }
            this->*member((Id) i) = Float((ScalarFloat) value);
        }
        m_specular = (SpecularModel) read_choice<2>(props, "specular", SpecularValues);
        m_surface_fresnel = read_choice<2>(props, "surface_fresnel", SurfaceFresnelValues) == 1;
        if (m_surface_fresnel && m_tau_given && !props.has_property("eta") &&
            !props.has_property("material"))
            Throw("powder: property \"surface_fresnel\" = \"fresnel\" needs the grain "
                  "material's index, which \"tau_o\" given alone does not fix: give \"eta\" "
                  "and \"k\" (or \"material\") too, or surface_fresnel = \"none\"");
        m_lobes = parse_lobes(props.get<std::string>("lobes", LobeList.def));
        m_cosine_only = read_choice<2>(props, "sampling", SamplingValues) == 1;
        m_conserving = read_choice<2>(props, "energy", EnergyValues) == 1;
        if (m_conserving)
            for (size_t i = 0; i < Count; ++i)
                if (is_normalisation_param((Id) i) && textured((Id) i))
                    Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                          "uniform \"%s\" (the normalisation is tabulated per wavelength and "
                          "incidence), but it is a texture; use energy = \"paper\" or a "
                          "float", Table[i].name);
        double wavelength = props.get<double>("wavelength", WavelengthNumber.def);
        check_range(WavelengthNumber.name, wavelength, WavelengthNumber.range);
        m_wavelength = (ScalarFloat) wavelength;
        std::array<double, 3> rgb = read_rgb_wavelengths(props);
        for (size_t i = 0; i < 3; ++i)
            m_rgb_wavelengths[i] = (ScalarFloat) rgb[i];
        m_optics = load_optics(props);
        if (props.has_property("albedo")) {
            m_albedo = props.get_texture<Texture>("albedo");
            Textures::check_albedo(m_albedo.get(), TableSize, TableMin);
            if (m_conserving && m_albedo->is_spatially_varying())
                Throw("powder: property \"energy\" = \"conserving\" needs a spatially "
                      "uniform albedo (the normalisation is tabulated per wavelength and "
                      "incidence), but property \"albedo\" is a spatially varying texture; "
                      "use energy = \"paper\" or a uniform albedo");
        }
    }

    /// The grain index at the wavelengths (nm) of the grain tables: a 1 nm grid for
    /// spectral variants, the evaluation wavelengths otherwise; with it tau_o (Fresnel)
    /// and the surface_fresnel index
    void read_grain_index() {
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
            m_tau_table = Tables::load(tau);
            m_tau_table_constant =
                std::all_of(tau.begin(), tau.end(), [&](ScalarFloat t) { return t == tau[0]; });
        }
        if (m_surface_fresnel)
            m_fresnel = Tables::fresnel_index(m_index, m_table_wavelengths);
    }

    /// Check every parameter in use (a value per lane: each lane), as after an edit
    void check_parameters() const {
        for (size_t i = 0; i < powder_param::Count; ++i) {
            powder_param::Id p = (powder_param::Id) i;
            if (!in_use(p))
                continue;
            if (m_textures[i]) {
                Textures::check(p, m_textures[i].get());
                continue;
            }
            const Float &v = this->*member(p);
            powder_param::check_lanes(p, v);
            // the grain tables are built from one value (one per lane would be ignored),
            // and so is the normalisation of energy = "conserving"
            if (dr::width(v) > 1 && m_conserving && powder_param::is_normalisation_param(p))
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

    /// Largest crystallite size parameter for which a mixing rule holds (docs/model.md)
    static constexpr double CrystalliteLimit = 0.5;

    /// Agglomerates: warn when the crystallites are too large for a mixing rule
    /// (size parameter 2 pi r |n + ik| / lambda above CrystalliteLimit at some wavelength)
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

    /// The value of a parameter that holds one value (lane 0 of a JIT array)
    template <typename T> static double value_of(const T &v) { return (double) dr::slice(v); }

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

    /// Whether a parameter enters the model as configured (range-checked, traversed)
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

    TextureValues<Float, Spectrum> texture_values(powder_param::Id p) const {
        return TextureValues<Float, Spectrum>::of(m_textures[p].get());
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

    /// Single-scattering albedo per channel: the `albedo` texture or the grain tables
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

    /// Spectral variants: (rho, tau_o) per channel from the records of m_packed, with the
    /// same linear interpolation as Tables::lookup in one packet gather per channel
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    lookup_grains(const SurfaceInteraction3f &si, Mask active) const {
        UnpolarizedSpectrum rho(0.f), tau(0.f);
        Tables::template read_records<4>(m_packed, si, active, [&](size_t c, auto value) {
            rho[c] = value(0);
            tau[c] = value(1);
        });
        return { rho, tau };
    }

    /// The grain tables after a change of the grain parameters (`keys`: those edited;
    /// none: all), and what eval reads of them
    void update_grains(const std::vector<std::string> &keys) {
        bool grains_changed = keys.empty();
        for (size_t i = 0; i < powder_param::Count; ++i)
            if (powder_param::is_grain_param((powder_param::Id) i))
                grains_changed |= string::contains(keys, powder_param::Table[i].name);
        if (!m_albedo && grain_textured())
            update_grain_texture_table();
        else if (!m_albedo && grains_changed)
            update_mie_tables();
        if (m_albedo && (keys.empty() || string::contains(keys, "albedo")))
            Textures::check_albedo(m_albedo.get(), TableSize, TableMin);

        if constexpr (is_spectral_v<Spectrum>) {
            // records (rho[i], rho[i + 1], tau[i], tau[i + 1]) for lookup_grains (zeros for
            // a table not in use); differentiable through the gathers from the tables
            FloatStorage zeros = dr::zeros<FloatStorage>(TableSize);
            m_packed = Tables::interval_records(
                { m_albedo ? &zeros : &m_mie.rho, m_tau_given ? &zeros : &m_tau_table },
                (uint32_t) TableSize);
        } else {
            // RGB and mono: one value per channel, as opaque scalars, so that eval reads a
            // broadcast value instead of gathering
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                if (!m_albedo)
                    m_rho_channels[c] = dr::gather<Float>(m_mie.rho, UInt32((uint32_t) c));
                if (!m_tau_given)
                    m_tau_channels[c] = dr::gather<Float>(m_tau_table, UInt32((uint32_t) c));
            }
            dr::make_opaque(m_rho_channels, m_tau_channels);
        }
    }

    /// The grains of the constant grain parameters
    powder::Grains grains() const {
        return { value_of(m_radius), value_of(m_radius2), value_of(m_fraction2),
                 m_two_populations, m_grain_model, value_of(m_agglomerate_radius),
                 value_of(m_agglomerate_fill), m_mixing };
    }

    /// The Mie tables; rho's derivatives are attached as tangents when gradients are
    /// tracked on a grain parameter
    void update_mie_tables() {
        std::vector<std::pair<const Float *, double powder::AlbedoRow::*>> params;
        for (auto [p, d] : { std::pair{ powder_param::Radius, &powder::AlbedoRow::d_r1 },
                             std::pair{ powder_param::Radius2, &powder::AlbedoRow::d_r2 },
                             std::pair{ powder_param::Fraction2, &powder::AlbedoRow::d_f2 },
                             std::pair{ powder_param::AgglomerateRadius,
                                        &powder::AlbedoRow::d_ra },
                             std::pair{ powder_param::AgglomerateFill,
                                        &powder::AlbedoRow::d_fill } })
            if (in_use(p))
                params.emplace_back(&(this->*member(p)), d);
        bool tangents = false;
        if constexpr (dr::is_diff_v<Float>)
            for (auto &gp : params)
                tangents |= dr::grad_enabled(*gp.first);
        if (!tangents)
            params.clear();
        m_mie = Tables::mie_tables(grains(), m_table_wavelengths, m_index, params);
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

    /// The grain parameter the texture table runs over (its texture sets the lanes): the
    /// first population's size (powder_registry.h), or the fill of agglomerates
    powder_param::Id table_param() const {
        if (agglomerate() && textured(powder_param::AgglomerateFill))
            return powder_param::AgglomerateFill;
        return powder_param::GrainRules[(size_t) m_grain_model].size;
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
        bool fill = table_param() == powder_param::AgglomerateFill;
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
                      powder_param::Table[table_param()].name, powder_param::Table[held].name);
        double held_value = agglomerate() ? value_of(this->*member(held)) : 0.0;
        auto [lo, hi] = value_range(table_param());
        if (m_two_populations && !agglomerate()) {
            auto [lo2, hi2] = value_range(powder_param::Radius2);
            lo = std::min(lo, lo2);
            hi = std::max(hi, hi2);
        }
        if (m_grain.table.nodes > 0 && lo >= m_grain_table_lo && hi <= m_grain_table_hi &&
            held_value == m_grain_table_held)
            return; // the current table covers the values
        powder::Grains g{ 1.0, 1.0, 0.0, false, m_grain_model, 1.0, 0.5, m_mixing };
        double lo_t, hi_t;
        if (fill) {
            // fills in (0, 1]: widened by 0.05 each way where they can be (a single
            // fill of 1 gets the interval [0.95, 1])
            lo_t = std::max(lo - 0.05, 0.5 * lo);
            hi_t = std::min(hi + 0.05, 1.0);
            g.agglomerate_radius = value_of(m_agglomerate_radius);
        } else {
            lo_t = lo / 1.25;
            hi_t = hi * 1.25;
            if (m_grain_model != powder::GrainModel::Slab) {
                // keep the widened range inside the size parameters Mie accepts
                auto [wl_lo, wl_hi] = std::minmax_element(m_table_wavelengths.begin(),
                                                          m_table_wavelengths.end());
                lo_t = std::max(lo_t, std::min(lo, 1e-3 * *wl_hi * 1e-3 / (2.0 * M_PI)));
                hi_t = std::min(hi_t, std::max(hi, 200.0 * *wl_lo * 1e-3 / (2.0 * M_PI)));
            }
            hi_t = std::max(hi_t, lo_t * 1.001);
            g.agglomerate_fill = value_of(m_agglomerate_fill);
        }
        build_grain_texture_table(g, lo, hi, lo_t, hi_t,
                                  fill ? powder::TableAxis::Fill : powder::TableAxis::LogRadius);
        m_grain_table_held = held_value;
    }

    /// Build the grain texture table over [lo_t, hi_t] of its variable (covering the
    /// texture values [lo, hi]) and upload its records
    void build_grain_texture_table(const powder::Grains &grains, double lo, double hi,
                                   double lo_t, double hi_t, powder::TableAxis axis) {
        bool fill = axis == powder::TableAxis::Fill;
        double error = 0.0;
        m_grain = Tables::grain_texture(powder::efficiency_table(
            grains, lo_t, hi_t, m_table_wavelengths, m_index,
            powder_param::Table[table_param()].name, GrainTableTolerance, GrainTableRecords,
            error, DrJitParallelFor(), axis));
        if (error > GrainTableTolerance)
            Log(Warn, "powder: the albedo table of %s %g-%g%s is accurate to %.2g "
                      "(relative, at the midpoints of its %zu nodes), not %g: the values "
                      "span too many Mie resonances for %zu records; narrow the texture's "
                      "range", fill ? "fills" : "radii", lo_t, hi_t, fill ? "" : " um",
                error, m_grain.table.nodes, GrainTableTolerance, GrainTableRecords);
        m_grain_table_lo = lo_t;
        m_grain_table_hi = hi_t;
        // a mean albedo for the sampling weights only: at the middle of the range
        double r_mid = fill ? 0.5 * (lo + hi) : std::sqrt(lo * hi), rho = 0.0;
        for (size_t i = 0; i < m_table_wavelengths.size(); ++i) {
            auto [qe, qs] = powder::efficiency_at(m_grain.table, i, r_mid);
            rho += qs / qe;
        }
        m_grain_rho_mean = rho / (double) m_table_wavelengths.size();
        // the constant-radius tables are not used; keep them valid for packing
        FloatStorage zeros = dr::zeros<FloatStorage>(m_table_wavelengths.size());
        m_mie = { zeros, zeros, zeros, zeros, zeros };
    }

    /// The albedo of spatially varying grains per lane (docs/model.md; slab: Q_ext = 1,
    /// Q_sca = rho)
    UnpolarizedSpectrum grain_texture_albedo(const SurfaceInteraction3f &si,
                                             Mask active) const {
        Float r1 = at(table_param(), si, active);
        if (!m_two_populations)
            return Tables::grain_albedo(m_grain, r1, nullptr, nullptr, si, active);
        Float r2 = at(powder_param::Radius2, si, active),
              f2 = at(powder_param::Fraction2, si, active);
        return Tables::grain_albedo(m_grain, r1, &r2, &f2, si, active);
    }

    // ---------------------------------------------------- volume constants

    /// An `albedo` that is one number for every wavelength and surface point (a
    /// `uniform` spectrum; in spectral variants the others depend on the wavelength)
    bool uniform_spectrum_albedo() const {
        return m_albedo && !m_albedo->is_spatially_varying() &&
               m_albedo->class_name() == "UniformSpectrum";
    }

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
     * (tests/test_autodiff.py). Only the cosines: a select of the x and y components
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

    // properties (read_properties)
    ref<Texture> m_albedo;                          ///< null: albedo from the grains
    Float m_av, m_g, m_kappa, m_tau_o, m_thickness, m_as, m_lc, m_sigma;
    Float m_radius, m_radius2, m_fraction2, m_agglomerate_radius, m_agglomerate_fill;
    ref<Texture> m_textures[powder_param::Count]; ///< texture-valued float parameters
    powder::GrainModel m_grain_model = powder::GrainModel::Sphere;
    powder::Mixing m_mixing = powder::Mixing::Bruggeman;
    bool m_tau_given = false, m_two_populations = false;
    SpecularModel m_specular;
    bool m_surface_fresnel = false, m_cosine_only = false;
    bool m_conserving = false;      ///< energy = "conserving"
    Lobes m_lobes;
    ScalarFloat m_wavelength;
    ScalarFloat m_rgb_wavelengths[3];
    uint32_t m_comp_volume = 0, m_comp_coherent = 0, m_comp_surface = 0;

    // grain tables (powder_tables.h), at the table wavelengths
    powder::OpticalTable m_optics;
    std::vector<double> m_table_wavelengths;       ///< nm
    std::vector<std::complex<double>> m_index;     ///< n + i k at those wavelengths
    typename Tables::MieTables m_mie;
    FloatStorage m_tau_table;
    bool m_tau_table_constant = false;     ///< every entry of m_tau_table is the same
    FloatStorage m_packed;                 ///< spectral: records for lookup_grains
    /// RGB and mono: the entries of the albedo and tau_o tables, one per channel
    UnpolarizedSpectrum m_rho_channels = 0.f, m_tau_channels = 0.f;
    typename Tables::FresnelIndex m_fresnel; ///< surface_fresnel
    /// spatially varying grains: the efficiency table (grain_texture_albedo), the
    /// values it covers and the agglomerate property it holds
    typename Tables::GrainTexture m_grain;
    double m_grain_table_lo = 0.0, m_grain_table_hi = 0.0, m_grain_table_held = 0.0;
    double m_grain_rho_mean = 0.5;

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
