#pragma once

/*
 * Importance sampling of the `powder` BSDF: the mixture of the cosine lobe with the
 * densities of powder_lobes.h (the coherent cone and the surface lobe), the share of the
 * samples each lobe gets (lobe_weights: rough estimates of each term's directional albedo)
 * and its width, and the mixture's density. The BSDF (powder.cpp) holds a PowderSampling
 * as a member, with the detached means these estimates read (update).
 */

#include "powder_grains.h"
#include "powder_lobes.h"
#include "powder_params.h"
#include "powder_tables.h"
#include "powder_terms.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> struct PowderSampling {
    MI_IMPORT_TYPES()
    using Params = PowderParams<Float, Spectrum>;
    using Grains = PowderGrains<Float, Spectrum>;
    using Tables = PowderTables<Float, Spectrum>;
    using Lobes = powder_param::Lobes;
    using SpecularModel = typename Params::SpecularModel;

    /// Probabilities of the coherent and surface sampling lobes (the cosine
    /// lobe gets the rest, at least 0.1) and their widths
    struct LobeWeights {
        Float coherent, surface;
        Float width_coherent; ///< scale of the projected 2D Cauchy lobe
        Float width_surface;  ///< std. dev. (projected plane or radians)
    };

    /// The detached means of the albedo and of tau_o after a parameter change (the
    /// estimates of lobe_weights read them)
    void update(const Params &p, const Grains &grains) {
        rho_mean = p.albedo ? dr::detach(p.albedo->mean())
                   : p.grain_textured() ? Float((ScalarFloat) grains.grain_rho_mean)
                   : Float(dr::mean(dr::detach(grains.mie.rho)));
        tau_mean = !p.tau_given ? Float(dr::mean(grains.tau_table))
                   : p.textured(powder_param::TauO)
                       ? Float(dr::detach(p.textures[powder_param::TauO]->mean()))
                       : dr::detach(p.tau_o);
        dr::make_opaque(rho_mean, tau_mean);
    }

    LobeWeights lobe_weights(const Params &p, const Grains &grains,
                             const SurfaceInteraction3f &si, Float lam_mean,
                             const Lobes &lobes) const {
        Float mu = dr::maximum(Frame3f::cos_theta(si.wi), 1e-4f);
        auto value = [&](powder_param::Id id) { return dr::detach(p.at(id, si, true)); };
        Float av = value(powder_param::AmplitudeVolume), rho = dr::clip(rho_mean, 0.f, 1.f),
              g = value(powder_param::G), kappa = value(powder_param::Extinction),
              tau = tau_mean, as = value(powder_param::AmplitudeSurface);

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
        auto [e_surface, width_s, wide] =
            surface_estimate(p, grains, si, lam_mean, mu, as, lobes);

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
        w.coherent = lobes.coherent && !p.cosine_only
            ? Float(.9f * e_coherent * inv_total) : Float(0.f);
        w.surface = !lobes.surface || p.cosine_only ? Float(0.f)
                    : surface_only ? dr::select(as > 0.f, 1.f - wide, 0.f)
                                   : dr::select(as > 0.f, .9f * e_surface * inv_total, 0.f) *
                                         (1.f - wide);
        w.width_coherent = width_c;
        w.width_surface = width_s;
        return w;
    }

    /// The surface lobe's estimated directional albedo, its width and the share of its
    /// probability that goes to the cosine lobe
    static std::tuple<Float, Float, Float>
    surface_estimate(const Params &p, const Grains &grains, const SurfaceInteraction3f &si,
                     const Float &lam_mean, const Float &mu, const Float &as,
                     const Lobes &lobes) {
        Float e_surface = 0.f, width_s, wide = 0.f;
        if (p.specular == SpecularModel::HarveyShack) {
            width_s = lam_mean * dr::InvPi<ScalarFloat> * dr::InvSqrtTwo<ScalarFloat> /
                      dr::detach(p.at(powder_param::CorrelationLength, si, true));
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
            width_s = dr::detach(p.at(powder_param::Sigma, si, true));
            if (lobes.surface)
                e_surface = as * width_s * dr::SqrtTwoPi<ScalarFloat> * mu;
        }
        // surface_fresnel: the lobe's energy follows the factor F(mu_i) / F(1) of the
        // mirror direction (channel mean), so that its share of the samples grows with it
        // towards grazing light
        if (lobes.surface && p.surface_fresnel) {
            UnpolarizedSpectrum f =
                dr::detach(Tables::fresnel_factor(grains.fresnel, si, mu, true));
            Float f_mean = 0.f;
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                f_mean += f[c];
            e_surface *= f_mean * (1.f / (ScalarFloat) dr::size_v<UnpolarizedSpectrum>);
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
    static Vector3f sample_surface(const Params &p, const Vector3f &wi, Float width,
                                   const Point2f &u) {
        if (p.specular == SpecularModel::HarveyShack)
            return powder::sample_projected<powder::Radial::Gaussian>(
                -wi.x(), -wi.y(), dr::square(Frame3f::cos_theta(wi)), width,
                surface_shift(wi, width), u);
        return powder::sample_angular(Vector3f(-wi.x(), -wi.y(), wi.z()), width, u);
    }

    static Float pdf_surface(const Params &p, const Vector3f &wi, const Vector3f &wo,
                             Float width) {
        if (p.specular == SpecularModel::HarveyShack)
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

    /// The density of the mixture (cosine, coherent and surface lobes with the weights w).
    /// A lobe of weight 0 adds nothing, whatever its density (a surface lobe far wider than
    /// the disc, e.g. l_c -> 0, has none in single precision)
    static Float pdf(const Params &p, const Lobes &lobes, const SurfaceInteraction3f &si,
                     const Vector3f &wo, const LobeWeights &w, Mask active) {
        Float mu_o = Frame3f::cos_theta(wo);
        Float density = (1.f - w.coherent - w.surface) * dr::InvPi<ScalarFloat> * mu_o;
        if (lobes.coherent)
            density += w.coherent * pdf_coherent(si.wi, wo, w.width_coherent);
        if (lobes.surface)
            density += w.surface * dr::select(w.surface > 0.f,
                                              pdf_surface(p, si.wi, wo, w.width_surface), 0.f);
        return dr::select(active && mu_o > 0.f, density, 0.f);
    }

    Float rho_mean, tau_mean; ///< detached means for the sampling weights (update)

    POWDER_TRAVERSE_MEMBERS(rho_mean, tau_mean)
};

NAMESPACE_END(mitsuba)
