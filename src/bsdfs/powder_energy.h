#pragma once

/*
 * energy = "conserving": the volume terms are multiplied by
 *     N(mu_i) = min(R_L, 1) / (R_L + R_C)   (per channel)
 * with R_L and R_C the directional-hemispherical reflectances of A_v (L1 + L2) / (4 pi)
 * and A_v C / (4 pi) at incidence mu_i, so that the volume part reflects min(R_L, 1).
 * N is tabulated on NormMu incidences with sqrt(mu_k) uniform from NormS0 to 1 (mu_k
 * from 4e-4 to 1, dense at grazing) per channel (RGB, mono) or per wavelength of a
 * NormStep grid over the spectral table, and interpolated linearly (in sqrt(mu_i) and
 * wavelength) by lookup. One quadrature for every backend: JIT variants evaluate all its
 * nodes in one kernel, scalar variants one after the other, summing in double.
 */

#include "powder_tables.h"
#include "powder_terms.h"

namespace powder {

/// Gauss-Legendre nodes x and weights w of n points on (0, 1), computed in double
template <typename T> void gauss_legendre01(uint32_t n, T *x, T *w) {
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
        x[i] = (T) (0.5 * (1.0 - z));
        w[i] = (T) (1.0 / ((1.0 - z * z) * pp * pp));
    }
}

/**
 * What the ladder terms reflect of light at normal incidence with energy = "paper": the
 * directional-hemispherical reflectance A_v / (4 pi) int (L1 + L2) mu_o dw_o =
 * (A_v / 2) int_0^1 (L1 + L2)(mu_o) mu_o dmu_o (at wi = +z both depend on mu_o alone), by a
 * 32-point Gauss-Legendre rule in double precision with the terms of powder_terms.h; L1 with
 * the thickness factor of kappa and d (d = inf: an infinite layer). `single`, `multiple`:
 * whether L1, L2 are evaluated. With the extrapolation ratio of the diffusion approximation
 * a white powder reflects about 0.75 tau_o + 0.44 (docs/powder.md, "Energy").
 */
inline double ladder_reflectance_normal(double rho, double g, double tau, double av,
                                        double kappa, double d, bool single, bool multiple) {
    constexpr uint32_t N = 32;
    double x[N], w[N];
    gauss_legendre01(N, x, w);
    using Vector = dr::Array<double, 3>;
    double c0 = std::sqrt(c0_squared(rho, g)), s_c0 = s_func(c0, tau), sum = 0.0;
    Vector wi(0.0, 0.0, 1.0);
    for (uint32_t i = 0; i < N; ++i) {
        double mu = x[i], f = 0.0;
        if (single)
            f += rho * single_scattering(g, wi, Vector(std::sqrt(1.0 - mu * mu), 0.0, mu),
                                         1.0 + mu) *
                 thickness_factor(kappa, d, 1.0, mu);
        if (multiple)
            f += multiple_scattering(3.0 * rho * rho, s_c0, c0, mu / (1.0 + mu), 1.0, mu);
        sum += w[i] * f * mu;
    }
    return 0.5 * av * sum;
}

} // namespace powder

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> struct PowderEnergy {
    MI_IMPORT_TYPES()
    using Tables = PowderTables<Float, Spectrum>;
    using FloatStorage = typename Tables::FloatStorage;
    static constexpr uint32_t C = (uint32_t) dr::size_v<UnpolarizedSpectrum>;
    static constexpr uint32_t NormMu = 24, NormPhi = 64, NormInner = 24, NormOuter = 24,
                              NormRadial = NormInner + NormOuter, NormQ = NormPhi * NormRadial;
    static constexpr float NormStep = 10.f; ///< nm, spectral variants
    static constexpr float NormS0 = .02f;   ///< sqrt(mu) of the first incidence node
    static constexpr uint32_t NormWavelengths = (uint32_t) ((Tables::TableSize - 1) / 10) + 1;
    /// Wavelengths (spectral) or channels of the table
    static constexpr uint32_t NW = is_spectral_v<Spectrum> ? NormWavelengths : C;
    /// Blocks of NormQ nodes: one per incidence node and group of C wavelengths
    static constexpr uint32_t Blocks = (NW + C - 1) / C * NormMu;

    /// Entries per record: the 2 incidence nodes bracketing mu_i of every channel (RGB: 6,
    /// padded to 8; mono: 2), or of 2 x 2 (wavelength, incidence) nodes (spectral: 4, one
    /// record per channel)
    static constexpr size_t NormPacket =
        is_spectral_v<Spectrum> ? 4 : (dr::size_v<UnpolarizedSpectrum> == 3 ? 8 : 2);

    /**
     * Node q of the quadrature of the projected disc at the incidence node `node`, in
     * polar coordinates (r, phi) about the back-scattering point c = wi_xy (where the
     * coherent cone sits): phi by the midpoint rule (NormPhi), r in [0, R(phi)] (R: the
     * rim) split at r1 = min(R, 0.05): Gauss-Legendre in log r on [r_min, r1] (the cone
     * can be 1e-3 wide), and in x on [r1, R] with r = R - (R - r1) x^2 (nodes dense at
     * the rim, where mu_o -> 0). Returns wi, wo and the weight of dA = mu_o dOmega.
     */
    static std::tuple<Vector3f, Vector3f, Float> node(const UInt32 &node, const UInt32 &q,
                                                      const FloatStorage &gx,
                                                      const FloatStorage &gw) {
        UInt32 j = q / NormRadial, i = q - j * NormRadial;
        Float t = NormS0 + Float(node) * ((1.f - NormS0) / (NormMu - 1)), mu = t * t,
              mu2 = mu * mu, cx = dr::sqrt(1.f - mu2);
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
    template <typename T> static T norm_from(const T &rl, const T &rc, const Float &av) {
        T total = rl + rc, av_pos = dr::select(av > 0.f, av, 1.f),
          cap = dr::select(av > 0.f, 4.f * dr::Pi<ScalarFloat> / av_pos, dr::Infinity<T>);
        dr::mask_t<T> ok = total > 0.f;
        return dr::select(ok, dr::minimum(rl, cap) / dr::select(ok, total, 1.f), 1.f);
    }

    /// The quadrature node of lane (block * NormQ + q): the interaction (its wavelengths,
    /// spectral) and wi, wo and the weight
    static std::tuple<SurfaceInteraction3f, Vector3f, Float> lane(const UInt32 &lane,
                                                                  const FloatStorage &gx,
                                                                  const FloatStorage &gw) {
        UInt32 block = lane / NormQ, q = lane - block * NormQ, group = block / NormMu,
               nd = block - group * NormMu;
        auto [wi, wo, weight] = node(nd, q, gx, gw);
        SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(dr::width(lane));
        si.wi = wi;
        if constexpr (is_spectral_v<Spectrum>)
            for (uint32_t c = 0; c < C; ++c)
                si.wavelengths[c] = Tables::TableMin +
                                    Float(dr::minimum(group * C + c, UInt32(NW - 1))) * NormStep;
        return { si, wo, weight };
    }

    /**
     * N per table wavelength (channel) and incidence node, at index wavelength * NormMu +
     * node; terms(si, wi, wo) gives (L1 + L2, C) without A_v / (4 pi), av is A_v.
     * Differentiable.
     */
    template <typename Terms> static FloatStorage table(const Terms &terms, const Float &av) {
        std::vector<ScalarFloat> x(NormRadial), w(NormRadial);
        powder::gauss_legendre01(NormInner, x.data(), w.data());
        powder::gauss_legendre01(NormOuter, x.data() + NormInner, w.data() + NormInner);
        FloatStorage gx = Tables::upload(x), gw = Tables::upload(w);
        std::vector<FloatStorage> norms(C); // per channel, per block
        if constexpr (dr::is_jit_v<Float>) {
            auto [si, wo, weight] = lane(dr::arange<UInt32>(Blocks * NormQ), gx, gw);
            auto [ladder, coherent] = terms(si, si.wi, wo);
            for (uint32_t c = 0; c < C; ++c)
                norms[c] = norm_from(dr::block_sum(ladder[c] * weight, NormQ),
                                    dr::block_sum(coherent[c] * weight, NormQ), av);
        } else {
            std::vector<double> rl(Blocks * C, 0.0), rc(Blocks * C, 0.0);
            for (uint32_t i = 0; i < Blocks * NormQ; ++i) {
                auto [si, wo, weight] = lane(i, gx, gw);
                auto [ladder, coherent] = terms(si, si.wi, wo);
                for (uint32_t c = 0; c < C; ++c) {
                    rl[i / NormQ * C + c] += (double) ladder[c] * weight;
                    rc[i / NormQ * C + c] += (double) coherent[c] * weight;
                }
            }
            for (uint32_t c = 0; c < C; ++c) {
                std::vector<ScalarFloat> v(Blocks);
                for (uint32_t b = 0; b < Blocks; ++b)
                    v[b] = norm_from((ScalarFloat) rl[b * C + c], (ScalarFloat) rc[b * C + c], av);
                norms[c] = Tables::upload(v);
            }
        }
        // table entry wl * NormMu + nd, wl = group * C + c: block group * NormMu + nd of c
        std::vector<const FloatStorage *> source;
        for (const FloatStorage &n : norms)
            source.push_back(&n);
        std::vector<uint32_t> which(NW * NormMu), index(NW * NormMu);
        for (uint32_t wl = 0; wl < NW; ++wl)
            for (uint32_t nd = 0; nd < NormMu; ++nd) {
                which[wl * NormMu + nd] = wl % C;
                index[wl * NormMu + nd] = wl / C * NormMu + nd;
            }
        return Tables::gather_entries(source, which, index);
    }

    /// The table as records of NormPacket entries for one packet gather per lookup
    static FloatStorage records(const FloatStorage &table) {
        constexpr uint32_t P = NormPacket;
        const uint32_t n_rec = is_spectral_v<Spectrum> ? NW * NormMu : NormMu;
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
        return Tables::gather_entries({ &table }, std::vector<uint32_t>(src.size(), 0u), src);
    }

    /// N at incidence mu_i and the channel wavelengths lam (um) from the records
    static UnpolarizedSpectrum lookup(const FloatStorage &records, const Float &mu_i,
                                      const UnpolarizedSpectrum &lam, Mask active) {
        Float t = dr::clip((dr::sqrt(mu_i) - NormS0) * ((NormMu - 1) / (1.f - NormS0)), 0.f,
                           (ScalarFloat) NormMu - 1.001f);
        // t >= 0: the signed conversions truncate to floor(t) (Tables::table_interval)
        Int32 k0_ = Int32(t);
        UInt32 k0 = UInt32(k0_);
        Float w = t - Float(k0_);
        UnpolarizedSpectrum out(0.f);
        using Packet = dr::Array<Float, NormPacket>;
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                Float s = dr::clip((lam[c] * 1e3f - Tables::TableMin) * (1.f / NormStep), 0.f,
                                   (ScalarFloat) NormWavelengths - 1.001f);
                Int32 j0_ = Int32(s);
                UInt32 j0 = UInt32(j0_);
                Float v = s - Float(j0_);
                Packet e = dr::gather<Packet>(records, j0 * NormMu + k0, active);
                out[c] = dr::lerp(dr::lerp(e[0], e[1], w), dr::lerp(e[2], e[3], w), v);
            }
        } else {
            Packet e = dr::gather<Packet>(records, k0, active);
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                out[c] = dr::lerp(e[2 * c], e[2 * c + 1], w);
        }
        return out;
    }
};

NAMESPACE_END(mitsuba)
