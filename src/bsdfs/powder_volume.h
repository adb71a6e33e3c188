#pragma once

/*
 * The volume constants of the model: the values of L2 and C that depend on the grains
 * (rho, g, tau_o) and not on the directions, and how eval obtains them (VolumePath):
 * computed per lane, once per parameter change, or read from a 1 nm table in spectral
 * variants. Powder::update_volume (after every parameter change) chooses the path by the
 * threshold here, and the form of C by those beside C (powder_terms.h).
 */

#include "powder_tables.h"
#include "powder_terms.h"

NAMESPACE_BEGIN(mitsuba)

/// How eval obtains the volume constants
enum class VolumePath {
    PerLane,      ///< from the albedo, tau_o and g at each interaction
    Uniform,      ///< the same for every interaction: once per parameter change
    UniformThick, ///< spectral, optically thick (optically_thick): once per change
    TableSTau,    ///< spectral, one-number albedo: records of (s(c0), tau_o)
    TableRho,     ///< spectral, grain albedo, optically thick: records of rho
    TableAll      ///< spectral: records of (rho, s(c0), tau_o)
};

inline bool uniform(VolumePath p) { return p == VolumePath::Uniform || p == VolumePath::UniformThick; }
inline bool tabulated(VolumePath p) {
    return p == VolumePath::TableSTau || p == VolumePath::TableRho || p == VolumePath::TableAll;
}
/// Optically thick: s(c) = 1 / (2 c) for every c >= c0, and tau_o is read by nothing
inline bool thick(VolumePath p) { return p == VolumePath::UniformThick || p == VolumePath::TableRho; }

/// The path in words (to_string, tests)
inline const char *describe(VolumePath p) {
    switch (p) {
        case VolumePath::Uniform: return "once per parameter change";
        case VolumePath::UniformThick: return "once per parameter change (optically thick)";
        case VolumePath::TableSTau: return "1 nm table of s(c0), tau_o";
        case VolumePath::TableRho: return "1 nm table of rho (optically thick)";
        case VolumePath::TableAll: return "1 nm table of rho, s(c0), tau_o";
        default: return "per lane";
    }
}

/**
 * Smallest x0 = 2 c0 tau_o (c0 from the albedo and g, tau_o its smallest value) for which
 * spectral variants treat the layer as optically thick: 18 ln 2, where exp(-x0) = 2^-18.
 * s(c) = (1 - exp(-2 c tau_o)) / (2 c) (docs/model.md Eq. 9b) depends on tau_o only
 * through exp(-2 c tau_o) <= exp(-x0) <= 2^-18 (3.8e-6) for every c >= c0: eval takes
 * s(c) = 1 / (2 c), so that neither L2 nor C depends on tau_o, the volume constants are
 * the same for every wavelength and computed once per parameter change, and eval reads
 * no table and skips the exponential of C. L2 and C change by at most 3.8e-6 relative
 * (tests/plugin/test_fast_paths.py); their derivatives with respect to the albedo and g by at
 * most x0 exp(-x0). The same holds for an albedo from the grain tables (table_thickness
 * bounds x0 over every interval of the 1 nm grid): the table then holds rho alone.
 */
constexpr double ThickLimit = 12.476649250079015;

template <typename Float, typename Spectrum> struct PowderVolume {
    MI_IMPORT_TYPES()
    using Tables = PowderTables<Float, Spectrum>;
    using FloatStorage = typename Tables::FloatStorage;
    using UInt64Storage = typename Tables::UInt64Storage;

    /// Per-channel values of the volume terms that depend on the grains only
    struct Constants {
        UnpolarizedSpectrum rho,
            rho2_3, ///< 3 rho^2, the prefactor of L2 and C
            c0_sq,  ///< c0^2 (powder::c0_squared)
            c0,
            s_c0,   ///< s(c0), docs/model.md Eq. 9b
            tau;    ///< tau_o
        DRJIT_STRUCT(Constants, rho, rho2_3, c0_sq, c0, s_c0, tau)
    };

    /// The constants of rho and g, without s(c0) (tau_o unset)
    static Constants without_s(const UnpolarizedSpectrum &rho, const Float &g) {
        Constants k;
        k.rho = rho;
        k.rho2_3 = 3.f * dr::square(rho);
        k.c0_sq = powder::c0_squared(rho, g);
        k.c0 = dr::sqrt(k.c0_sq);
        return k;
    }

    static Constants constants(const UnpolarizedSpectrum &rho, const UnpolarizedSpectrum &tau,
                               const Float &g) {
        Constants k = without_s(rho, g);
        k.tau = tau;
        k.s_c0 = powder::s_func(k.c0, tau);
        return k;
    }

    /// Smallest entry of a table (detached), as a double
    static double min_of(const FloatStorage &t) {
        if constexpr (dr::is_jit_v<Float>) {
            return (double) dr::slice(dr::min(dr::detach(t)));
        } else {
            double m = powder_param::Inf;
            for (size_t i = 0; i < t.size(); ++i)
                m = std::min(m, (double) t[i]);
            return m;
        }
    }

    /**
     * Lower bound of x0 = 2 c0 tau_o over the 1 nm grid with rho and tau_o interpolated
     * linearly between its nodes (and c0 from rho and the one g): on each interval, rho is
     * at most the larger of its two nodes, c0 (which decreases as rho grows, for every g in
     * [-1, 1]) at least c0 of that, and tau_o at least the smaller node.
     */
    static double table_thickness(const FloatStorage &rho_, const FloatStorage &tau_,
                                  const Float &g_) {
        const uint32_t n = (uint32_t) dr::width(rho_);
        FloatStorage rho = dr::detach(rho_), tau = dr::detach(tau_);
        FloatStorage lo = Tables::interval_records({ &rho, &tau }, n);
        Float g = dr::detach(g_);
        double x0 = powder_param::Inf;
        if constexpr (dr::is_jit_v<Float>) {
            auto r = dr::gather<dr::Array<Float, 4>>(lo, dr::arange<UInt32>(n));
            Float rho_hi = dr::maximum(r[0], r[1]), tau_lo = dr::minimum(r[2], r[3]);
            x0 = min_of(FloatStorage(2.f * dr::sqrt(powder::c0_squared(rho_hi, g)) * tau_lo));
        } else {
            for (uint32_t i = 0; i < n; ++i) {
                double r = std::max((double) lo[4 * i], (double) lo[4 * i + 1]),
                       t = std::min((double) lo[4 * i + 2], (double) lo[4 * i + 3]);
                x0 = std::min(x0, 2.0 * std::sqrt(powder::c0_squared(r, (double) g)) * t);
            }
        }
        return x0;
    }

    /// Spectral variants: the volume constants per channel from the table of `path` (one
    /// packet gather per channel; linear in wavelength on the 1 nm grid); `uniform` holds
    /// what the table does not (rho and c0 of a one-number albedo, tau_o when thick)
    static Constants lookup(const FloatStorage &table, const UInt64Storage &pairs,
                            VolumePath path, const Constants &uniform, const Float &g,
                            const SurfaceInteraction3f &si, Mask active) {
        Constants k;
        if (path == VolumePath::TableSTau) {
            Tables::template read_records<4>(table, si, active, [&](size_t c, auto value) {
                k.s_c0[c] = value(0);
                k.tau[c] = value(1);
            });
            k.rho = uniform.rho;
            k.rho2_3 = uniform.rho2_3;
            k.c0_sq = uniform.c0_sq;
            k.c0 = uniform.c0;
        } else {
            UnpolarizedSpectrum rho, s_c0, tau;
            if (path == VolumePath::TableRho && dr::width(pairs) != 0 &&
                !dr::grad_enabled(table)) // (packed_pairs: the same values)
                Tables::read_pairs(pairs, si, active,
                                   [&](size_t c, const Float &value) { rho[c] = value; });
            else if (path == VolumePath::TableRho)
                Tables::template read_records<2>(table, si, active,
                                                 [&](size_t c, auto value) { rho[c] = value(0); });
            else // records of (rho, s(c0), tau_o, padding)
                Tables::template read_records<8>(table, si, active, [&](size_t c, auto value) {
                    rho[c] = value(0);
                    s_c0[c] = value(1);
                    tau[c] = value(2);
                });
            k = without_s(rho, g); // the same c0 as the per-lane path
            if (path == VolumePath::TableRho) { // s(c0) = 1 / (2 c0): see ThickLimit
                k.s_c0 = .5f / k.c0;
                k.tau = uniform.tau;
            } else {
                k.s_c0 = s_c0;
                k.tau = tau;
            }
        }
        // masked lanes read zeros: tau_o = 1 there keeps x = 2 c tau_o > 0 in the closed
        // forms of C (no 0 / 0 in lanes that are discarded anyway)
        k.tau = dr::select(active, k.tau, 1.f);
        return k;
    }

    /**
     * Spectral variants, when the volume constants depend on the wavelength only (the
     * albedo `rho` per node of the 1 nm grid, or one number `rho_given`; tau_o per node; one
     * g): their table (lookup), as records of the two nodes bracketing each interval:
     * (rho, s(c0), tau_o) per node, or (s(c0), tau_o) when the albedo is one number (rho
     * and c0 in `uniform`), or rho alone when optically thick at every wavelength (ThickLimit;
     * tau_o, which neither L2 nor C then reads, its smallest value in `uniform`). rho and
     * tau_o are interpolated linearly in wavelength, c0 computed from rho; s(c0) is
     * interpolated instead of recomputed (L2 differs by 2.3e-5 relative for a Mie albedo of
     * 100 nm grains, 7.7e-5 for a mix with 300 nm grains, tests/plugin/test_fast_paths.py): eval
     * then computes no exponential and no division for it. Differentiable. Returns the
     * path; `x0` receives a lower bound of 2 c0 tau_o over the interpolated values.
     */
    static VolumePath build_table(const FloatStorage &rho, const Float *rho_given,
                                  const FloatStorage &tau, const Float &g, Constants &uniform,
                                  FloatStorage &table, UInt64Storage &pairs, double &x0) {
        const uint32_t n = (uint32_t) dr::width(tau);
        FloatStorage gs = broadcast(g, n), c0_sq = powder::c0_squared(rho, gs),
                     s_c0 = powder::s_func(dr::sqrt(c0_sq), tau);
        VolumePath path = VolumePath::TableAll;
        if (rho_given) {
            path = VolumePath::TableSTau;
            Constants k = without_s(UnpolarizedSpectrum(*rho_given), g);
            uniform.rho = k.rho;
            uniform.rho2_3 = k.rho2_3;
            uniform.c0_sq = k.c0_sq;
            uniform.c0 = k.c0;
            dr::make_opaque(uniform.rho, uniform.rho2_3, uniform.c0_sq, uniform.c0);
        } else if (table_thickness(rho, tau, g) * (1.0 - powder::SaturationMargin) >= ThickLimit) {
            path = VolumePath::TableRho;
            uniform.tau = UnpolarizedSpectrum(Float(dr::min(dr::detach(tau))));
            dr::make_opaque(uniform.tau);
        }
        std::vector<const FloatStorage *> quantities;
        if (path == VolumePath::TableSTau)
            quantities = { &s_c0, &tau };
        else if (path == VolumePath::TableRho)
            quantities = { &rho };
        else // (padding to a packet of 8)
            quantities = { &rho, &s_c0, &tau, &tau };
        table = Tables::interval_records(quantities, n);
        // rho alone: also as 64-bit words, one hardware gather per channel (read_pairs)
        pairs = path == VolumePath::TableRho ? Tables::packed_pairs(table) : UInt64Storage();
        x0 = 2.0 * std::sqrt(std::max(min_of(c0_sq), 0.0)) * min_of(tau);
        return path;
    }

    /// n copies of a one-value parameter, differentiable
    static FloatStorage broadcast(const Float &v, size_t n) {
        if constexpr (dr::is_jit_v<Float>)
            return v + dr::zeros<FloatStorage>(n);
        else
            return dr::full<FloatStorage>(v, n);
    }
};

NAMESPACE_END(mitsuba)
