#pragma once

/*
 * The terms of the model (docs/model.md, Eq. 9, 10, 20-22), one function each, as
 * templates over Dr.Jit types (scalar or JIT; Spectrum: one value per channel), in the
 * order of tests/oracles/model.py: s(c), the Henyey-Greenstein phase function with L1, the
 * volume constant c0, L2, C and the two surface terms S. The BSDF composes them into
 * Eq. 23 (powder.cpp, eval_brdf); none reads the plugin's state.
 */

#include "powder_math.h"

#include <algorithm>
#include <type_traits>

namespace powder {

/// docs/model.md, Eq. 9b: s(c) = (1 - exp(-2 c tau_o)) / (2 c), equal to tau_o at c = 0
template <typename T> T s_func(const T &c, const T &tau) {
    return tau * one_minus_exp_neg_over_x(2.f * c * tau);
}

/**
 * L1 / rho without the thickness factor (docs/model.md, Eq. 9a): P(Theta) / (mu_i + mu_o)
 * with the Henyey-Greenstein P = (1 - g^2) / t^(3/2), t = 1 + g^2 - 2 g cos(Theta),
 * cos(Theta) = -dot(wi, wo), rewritten with non-negative terms so that it keeps its
 * precision when |g| -> 1: with sg = sign(g) (+1 at g = 0),
 * t = (1 - |g|)^2 + |g| |wi + sg wo|^2 (|g| written as sg g: the derivative of dr::abs
 * at g = 0 is 0, which would give a wrong d/dg at the default g = 0)
 */
template <typename Float, typename Vector3f>
Float single_scattering(const Float &g, const Vector3f &wi, const Vector3f &wo,
                        const Float &mu_sum) {
    Float sg = dr::select(g >= 0.f, 1.f, -1.f), abs_g = sg * g,
          t = dr::square(1.f - abs_g) + abs_g * dr::squared_norm(dr::fmadd(sg, wo, wi));
    // P(Theta) / (mu_i + mu_o) as one division
    return (1.f - dr::square(g)) / (t * dr::sqrt(t) * mu_sum);
}

/// The factor of a layer of finite thickness d in L1: 1 - exp(-kappa d (1/mu_i + 1/mu_o));
/// 1 where d is infinite, with no 0 * inf in the gradient of the extinction
template <typename Float>
Float thickness_factor(const Float &kappa, const Float &d, const Float &mu_i,
                       const Float &mu_o) {
    dr::mask_t<Float> infinite = dr::isinf(d);
    return dr::select(infinite, 1.f,
                      one_minus_exp_neg(kappa * dr::select(infinite, 0.f, d) *
                                        (dr::rcp(mu_i) + dr::rcp(mu_o))));
}

/// c0^2 = 3 (1 - rho) (1 - rho g) (docs/model.md, Eq. 10e with alpha = 0), at least 0;
/// c0 = sqrt(c0^2) sets L2 and C
template <typename T, typename G> T c0_squared(const T &rho, const G &g) {
    T c0_sq = 3.f * (1.f - rho) * (1.f - rho * g);
    if constexpr (std::is_arithmetic_v<T>)
        return std::max(c0_sq, T(0));
    else
        return dr::maximum(c0_sq, 0.f);
}

/// L2, docs/model.md Eq. 9b (corrected): 3 rho^2 [s(c0) + h] / ((1 + c0 mu_i) (1 + c0 mu_o)),
/// h = mu_i mu_o / (mu_i + mu_o); rho2_3 = 3 rho^2
template <typename Spectrum, typename Float>
Spectrum multiple_scattering(const Spectrum &rho2_3, const Spectrum &s_c0, const Spectrum &c0,
                             const Float &h, const Float &mu_i, const Float &mu_o) {
    return rho2_3 * (s_c0 + h) / ((1.f + c0 * mu_i) * (1.f + c0 * mu_o));
}

/// L2 of an optically thick layer, where s(c0) = 1 / (2 c0) (powder_volume.h, ThickLimit):
/// 3 rho^2 (1 + 2 c0 h) / (2 c0 (1 + c0 mu_i) (1 + c0 mu_o)), one division where
/// multiple_scattering with s(c0) = 1 / (2 c0) takes two (c0 > 0 there)
template <typename Spectrum, typename Float>
Spectrum multiple_scattering_thick(const Spectrum &rho2_3, const Spectrum &c0, const Float &h,
                                   const Float &mu_i, const Float &mu_o) {
    return rho2_3 * dr::fmadd(c0, 2.f * h, 1.f) /
           ((2.f * c0) * ((1.f + c0 * mu_i) * (1.f + c0 * mu_o)));
}

/// How C evaluates (1 - exp(-x)) / x, x = 2 c tau_o >= x0 = 2 c0 tau_o (coherent_form)
enum class CoherentForm {
    Saturated,  ///< 1 - exp(-x) == 1 in single precision for every x (or optically thick)
    ClosedForm, ///< x >= CoherentSeriesLimit everywhere: no series
    WithSeries  ///< some x may be small: the series below CoherentSeriesLimit
};

/// Smallest x = 2 c tau_o from which 1 - exp(-x) rounds to 1 in single precision
/// (exp(-18) < 2^-25); C skips the exponential there
constexpr double CoherentSaturation = 18.0;

/// Smallest x = 2 c tau_o for which C takes (1 - exp(-x)) / x in closed form
/// (below it, its series: powder::one_minus_exp_neg_over_x)
constexpr double CoherentSeriesLimit = 0.03;

/// Relative margin by which x0, computed in double from single-precision values, must
/// clear the limits (eval's x in single precision can be a few ulp below it)
constexpr double SaturationMargin = 1e-5;

/// The form of C for a lower bound x0 of x over every lane, channel and table node
/// (`thick`: s(c) = 1 / (2 c) holds for every c, whatever x0)
inline CoherentForm coherent_form(double x0, bool thick) {
    x0 *= 1.0 - SaturationMargin;
    if (thick || x0 >= CoherentSaturation)
        return CoherentForm::Saturated;
    return x0 >= CoherentSeriesLimit ? CoherentForm::ClosedForm : CoherentForm::WithSeries;
}

/**
 * C, docs/model.md Eq. 9c with Eq. 10: 3 rho^2 [1/(2v) + s(c)] / (mu_i mu_o ((c + v)^2 + u^2)),
 * alpha = (k0 / kappa) |wo_xy - wi_xy|, c = sqrt(c0^2 + alpha^2), u = (k0 / kappa) (mu_i - mu_o),
 * 1/(2v) = h. The denominator written without 1/mu (no square root of mu_i mu_o, one
 * division fewer): with p = 2 mu_i mu_o, 4 mu_i mu_o [mu_i mu_o ((c + v)^2 + u^2)] =
 * (c p + mu_i + mu_o)^2 + (k0 / kappa)^2 ((mu_i - mu_o) p)^2 =: D, so
 * C = 3 rho^2 2 p [h + s(c)] / D, with h + s(c) = [h x + tau (1 - exp(-x))] / x, x = 2 c tau.
 */
template <typename Spectrum, typename Float, typename Vector3f>
Spectrum coherent(const Spectrum &rho2_3, const Spectrum &c0_sq, const Spectrum &tau,
                  const Spectrum &k0_kappa, const Vector3f &wi, const Vector3f &wo,
                  const Float &mu_i, const Float &mu_o, const Float &h, CoherentForm form) {
    Float dx = wo.x() - wi.x(), dy = wo.y() - wi.y(), mu_sum = mu_i + mu_o,
          p = 2.f * (mu_i * mu_o), up2 = dr::square((mu_i - mu_o) * p);
    Spectrum k0_kappa2 = dr::square(k0_kappa),
             c = dr::sqrt(c0_sq + k0_kappa2 * (dx * dx + dy * dy)),
             D = dr::square(dr::fmadd(c, p, mu_sum)) + k0_kappa2 * up2,
             x = c * (2.f * tau), prefactor = rho2_3 * (2.f * p);
    if (form == CoherentForm::Saturated) // s(c) = 1 / (2 c), whatever tau_o > 0
        return prefactor * dr::fmadd(h, x, tau) / (x * D);
    if (form == CoherentForm::ClosedForm)
        return prefactor * dr::fmadd(h, x, tau * (1.f - exp_neg(dr::minimum(x, 20.f)))) /
               (x * D);
    auto small = x < (float) CoherentSeriesLimit;
    Spectrum xs = dr::select(small, x, 0.f), xl = dr::select(small, 1.f, x),
             series = one_minus_exp_neg_over_x_series(xs),
             // (the clamp as in one_minus_exp_neg: no value changes)
             one_minus_e = 1.f - exp_neg(dr::minimum(xl, 20.f)),
             num = dr::select(small, h + tau * series, dr::fmadd(h, xl, tau * one_minus_e));
    return prefactor * num / (xl * D);
}

/**
 * S, docs/model.md Eq. 21-22 (Harvey-Shack, Gaussian PSD):
 * A_s' (4 pi^2 / lam^4) (mu_i + mu_o)^2 pi l_c^2 exp(-pi^2 l_c^2 f_s^2), f_s = |wo_xy + wi_xy| / lam,
 * with inv_lam = 1 / lam per channel (1/um)
 */
template <typename Spectrum, typename Float, typename Vector3f>
Spectrum surface_harvey_shack(const Float &as, const Float &lc, const Vector3f &wi,
                              const Vector3f &wo, const Float &mu_sum, const Spectrum &inv_lam) {
    using Scalar = dr::scalar_t<Float>;
    Float sx = wo.x() + wi.x(), sy = wo.y() + wi.y(), lc2 = dr::square(lc),
          // the factors that do not depend on lambda, grouped so that the parameters'
          // product is computed once per kernel, not per lane
          prefactor = (as * (4.f * dr::Pi<Scalar> * dr::square(dr::Pi<Scalar>)) * lc2) *
                      dr::square(mu_sum),
          // pi^2 l_c^2 |wo_xy + wi_xy|^2 / ln 2 (exp2_neg takes base-2 exponents)
          t = (dr::square(dr::Pi<Scalar>) * dr::InvLogTwo<Scalar> * lc2) * (sx * sx + sy * sy);
    Spectrum inv_lam2 = dr::square(inv_lam);
    return prefactor * dr::square(inv_lam2) * exp2_neg(t * inv_lam2);
}

/// S, docs/model.md Eq. 20 (Gaussian in the angle theta_s to the mirror direction):
/// A_s / (sigma sqrt(2 pi)) exp(-theta_s^2 / (2 sigma^2))
template <typename Float>
Float surface_gaussian(const Float &as, const Float &sigma, const Float &theta_s) {
    using Scalar = dr::scalar_t<Float>;
    return as * dr::InvSqrtTwoPi<Scalar> / sigma *
           exp_neg(dr::square(theta_s) / (2.f * dr::square(sigma)));
}

} // namespace powder
