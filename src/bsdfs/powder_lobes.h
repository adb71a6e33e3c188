#pragma once

/*
 * Numerical helpers and importance-sampling lobes of the `powder` BSDF, as free
 * function templates over Dr.Jit types (scalar or JIT), outside the BSDF class.
 *
 * Every lobe is an exact, normalised density on the upper hemisphere: a lobe is
 * written in polar coordinates (r, e) about its centre, and r follows the lobe's
 * radial law truncated where the ray from the centre along e leaves the
 * hemisphere. So no sample is ever produced below the horizon, and `pdf` equals
 * the density that `sample` draws from (no mass is lost off the disc).
 *
 *  - projected lobes (coherent cone, Harvey-Shack surface lobe) live in the
 *    projected plane (wo_x, wo_y) and are truncated at the unit disc; their
 *    solid-angle density is the area density times mu_o;
 *  - the Gaussian surface lobe lives in the tangent plane of the mirror direction
 *    (exponential map, theta = angle to the mirror direction) and is truncated
 *    at the horizon along each great circle through the mirror direction.
 */

#include <drjit/math.h>

#include <tuple>
#include <utility>

namespace powder {

namespace dr = drjit;
template <typename T> using Mask = dr::mask_t<T>;

// ------------------------------------------------------------ exp(-x)

/// Base-2 exponent beyond which exp2_neg and exp_neg return 0 (2^-64 = 5.4e-20)
constexpr float ExpNegCut2 = 64.f;

/**
 * 2^-t for t >= 0 (and +inf), for the exponentials of eval (the surface lobes, the
 * coherent term below saturation, finite thickness) and of the sampling densities.
 * JIT variants: -t = n + f with n the nearest integer and |f| <= 1/2, 2^f from the
 * degree-6 polynomial of Cephes' exp2f, 2^n from the exponent bits; within 3 ulp
 * of dr::exp2 at the same argument (tests/test_fast_paths.py), in 19 operations of the
 * LLVM kernel where dr::exp takes 22 (it also handles overflow, which these arguments
 * cannot reach). Scalar variants, and
 * arguments that carry gradients (Dr.Jit's exact derivative rule), call dr::exp2.
 *
 * t > ExpNegCut2 gives 0 in every variant. These values are always multiplied by a
 * prefactor, and the products can be denormal floats (below 1.2e-38), which are
 * slow to compute with: on the AMD EPYC of docs/benchmarks.md, a version that returned
 * 2^-125 instead of 0 (denormal products in most lanes of the Gaussian surface lobe)
 * made that eval 1.5-1.6 times slower. A term below 5.4e-20 of its prefactor is far
 * below the float resolution of any sum it enters.
 */
template <typename T> T exp2_neg(const T &t) {
    T value;
    if constexpr (dr::is_jit_v<T>) {
        if (dr::grad_enabled(t)) {
            value = dr::exp2(-t);
        } else {
            using Int = dr::int32_array_t<T>;
            T y = -dr::minimum(t, ExpNegCut2), n = dr::round(y), f = y - n;
            T p = dr::estrin(f, 1.f, 6.931472028550421e-1f, 2.402264791363012e-1f,
                             5.550332471162809e-2f, 9.618437357674640e-3f,
                             1.339887440266574e-3f, 1.535336188319500e-4f);
            value = p * dr::reinterpret_array<T>(dr::sl<23>(Int(n) + 0x7f));
        }
    } else {
        value = dr::exp2(-t);
    }
    return dr::select(t > ExpNegCut2, 0.f, value);
}

/// exp(-x) for x >= 0 (and +inf): exp2_neg(x / ln 2) in JIT variants, dr::exp(-x)
/// in scalar variants and where x carries gradients; 0 where x > 64 ln 2 = 44.4
template <typename T> T exp_neg(const T &x) {
    if constexpr (dr::is_jit_v<T>) {
        if (!dr::grad_enabled(x))
            return exp2_neg(x * dr::InvLogTwo<float>);
    }
    return dr::select(x > ExpNegCut2 * dr::LogTwo<float>, 0.f, dr::exp(-x));
}

// ------------------------------------------------------------ 1 - exp(-x)

/// The series of (1 - exp(-x)) / x, for 0 <= x < 0.03 (truncation error below
/// x^5 / 720 < 4e-11)
template <typename T> T one_minus_exp_neg_over_x_series(const T &x) {
    return 1.f - x * .5f * (1.f - x * (1.f / 3.f) * (1.f - x * .25f * (1.f - x * .2f)));
}

/// 1 - exp(-x) for x >= 0, accurate for small x (Dr.Jit has no expm1)
template <typename T> T one_minus_exp_neg(const T &x) {
    dr::mask_t<T> small = x < 0.03f;
    T xs = dr::select(small, x, 0.f), xl = dr::select(small, 1.f, x);
    // exp(-x) < 2^-25 for x > 17.4: 1 - exp(-x) rounds to 1, so clamping the
    // argument at 20 changes no value and keeps exp away from denormal results
    return dr::select(small, xs * one_minus_exp_neg_over_x_series(xs),
                      1.f - exp_neg(dr::minimum(xl, 20.f)));
}

/// (1 - exp(-x)) / x for x >= 0, equal to 1 at x = 0
template <typename T> T one_minus_exp_neg_over_x(const T &x) {
    dr::mask_t<T> small = x < 0.03f;
    T xs = dr::select(small, x, 0.f), xl = dr::select(small, 1.f, x);
    return dr::select(small, one_minus_exp_neg_over_x_series(xs),
                      (1.f - exp_neg(dr::minimum(xl, 20.f))) / xl);
}

/// MODEL.md, Eq. 9b: s(c) = (1 - exp(-2 c tau_o)) / (2 c), equal to tau_o at c = 0
template <typename T> T s_func(const T &c, const T &tau) {
    return tau * one_minus_exp_neg_over_x(2.f * c * tau);
}

/// -log(1 - x) for 0 <= x < 1, accurate for small x (Dr.Jit has no log1p)
template <typename T> T neg_log_one_minus(const T &x) {
    T w = 1.f - x;
    // log(w) * x / (1 - w) corrects the rounding of w (Goldberg's log1p)
    return dr::select(w == 1.f, x, -dr::log(w) * (x / (1.f - w)));
}

// ---------------------------------------------------------- projected lobes

/// Distance from the point c of the unit disc along the unit direction e to the
/// disc's rim: the positive root R of |c + R e| = 1, with ce = dot(c, e) and
/// one_minus_c2 = 1 - |c|^2 (= mu^2 for c = +-wi_xy, passed exactly)
template <typename Float> Float disc_exit(const Float &ce, const Float &one_minus_c2) {
    Float root = dr::sqrt(dr::maximum(dr::square(ce) + one_minus_c2, 0.f));
    return dr::select(ce > 0.f, one_minus_c2 / (ce + root), root - ce);
}

/// Radial laws of the projected lobes (2D densities of the distance r to the
/// centre, per unit area, before truncation), scale `s`:
///   Gaussian: exp(-r^2 / (2 s^2)) / (2 pi s^2)
///   Cauchy:   s / (2 pi (r^2 + s^2)^(3/2))
enum class Radial { Gaussian, Cauchy };

/// Mass of the radial law within radius R
template <Radial law, typename Float> Float radial_mass(const Float &R, const Float &s) {
    if constexpr (law == Radial::Gaussian) {
        return one_minus_exp_neg(dr::square(R) / (2.f * dr::square(s)));
    } else {
        Float h = dr::sqrt(dr::square(R) + dr::square(s));
        return dr::square(R) / (h * (h + s)); // = 1 - s / h, without cancellation
    }
}

/// Radius of mass fraction `m` (inverse of radial_mass), 0 <= m < 1
template <Radial law, typename Float> Float radial_inverse(const Float &m, const Float &s) {
    if constexpr (law == Radial::Gaussian) {
        return s * dr::sqrt(2.f * neg_log_one_minus(m));
    } else {
        return s * dr::sqrt(m * (2.f - m)) / (1.f - m);
    }
}

/// Area density of the radial law at squared distance r2 (not truncated)
template <Radial law, typename Float> Float radial_density(const Float &r2, const Float &s) {
    if constexpr (law == Radial::Gaussian) {
        Float inv_var = dr::rcp(dr::square(s));
        return inv_var * dr::InvTwoPi<Float> * exp_neg(.5f * r2 * inv_var);
    } else {
        Float t = r2 + dr::square(s);
        return s * dr::InvTwoPi<Float> / (t * dr::sqrt(t));
    }
}

// ------------------------------------------------ directions about a centre

/*
 * Every lobe is sampled in polar coordinates (r, e) about its centre c: first a
 * unit direction e, then r along e from the lobe's radial law truncated at the
 * boundary. Uniform directions would put as many samples on the short rays of a
 * centre near the boundary as on the long ones, all crowded next to the centre;
 * so e is the direction, seen from c, of a uniform point of a unit disc in which
 * c lies at kappa * c_hat (c_hat: unit vector from the disc centre towards c).
 * kappa = 0 (uniform directions) while the lobe lies well inside the boundary,
 * growing to |c| (e spread like the area of the disc seen from c) when the lobe
 * is wider than the distance d = 1 - |c| from c to the boundary. The density of
 * e per radian is R_gen(e)^2 / (2 pi), R_gen = distance from c to the rim of that
 * disc along e.
 */

/// Skew kappa of the direction law for a lobe of scale s (unit-disc units) about
/// a centre at distance c_norm from the disc centre, d = 1 - c_norm
template <typename Float> Float direction_skew(const Float &c_norm, const Float &d,
                                               const Float &s) {
    return c_norm * dr::maximum(0.f, 1.f - d / (2.f * s));
}

/// Unit direction e = (ex, ey) seen from kappa * c_hat of a uniform point of the
/// unit disc drawn from (u1, u2) in [0, 1)^2
template <typename Float>
std::pair<Float, Float> sample_direction(const Float &kappa, const Float &chx,
                                         const Float &chy, const Float &u1, const Float &u2) {
    auto [sin_p, cos_p] = dr::sincos(dr::TwoPi<Float> * u2);
    Float q = dr::sqrt(u1), dx = q * cos_p - kappa * chx, dy = q * sin_p - kappa * chy;
    Float n = dr::sqrt(dx * dx + dy * dy);
    Mask<Float> ok = n > 0.f;
    Float inv = dr::select(ok, dr::rcp(n), 0.f);
    return { dr::select(ok, dx * inv, chx), dr::select(ok, dy * inv, chy) };
}

/// 2 pi times the density per radian of sample_direction at e, with ce_hat =
/// dot(c_hat, e)
template <typename Float> Float direction_density(const Float &kappa, const Float &ce_hat) {
    return dr::square(disc_exit(kappa * ce_hat, 1.f - dr::square(kappa)));
}

// ---------------------------------------------------------- projected lobes

/// Unit vector from the disc centre towards c (any unit vector if c = 0)
template <typename Float>
std::tuple<Float, Float, Float> centre_direction(const Float &cx, const Float &cy) {
    Float n = dr::sqrt(cx * cx + cy * cy);
    Mask<Float> ok = n > 0.f;
    Float inv = dr::select(ok, dr::rcp(n), 0.f);
    return { n, dr::select(ok, cx * inv, 1.f), dr::select(ok, cy * inv, 0.f) };
}

/**
 * Sample a projected lobe of scale s centred on the point (cx, cy) of the unit
 * disc, with one_minus_c2 = 1 - cx^2 - cy^2 (= mu^2 for c = +-wi_xy, passed
 * exactly): direction e from sample_direction (u3, u.y), r from the radial law
 * truncated at the disc's rim along e (u.x). Returns the direction (mu_o >= 0).
 */
template <Radial law, typename Float, typename Point2f>
dr::Array<Float, 3> sample_projected(const Float &cx, const Float &cy,
                                     const Float &one_minus_c2, const Float &s,
                                     const Point2f &u, const Float &u3) {
    auto [c_norm, chx, chy] = centre_direction(cx, cy);
    Float kappa = direction_skew(c_norm, one_minus_c2 / (1.f + c_norm), s);
    auto [ex, ey] = sample_direction(kappa, chx, chy, u3, u.y());
    Float ce = cx * ex + cy * ey, R = disc_exit(ce, one_minus_c2);
    Float r = dr::minimum(radial_inverse<law>(u.x() * radial_mass<law>(R, s), s), R);
    // 1 - |c + r e|^2 = (R - r) (R + r + 2 c.e), without cancellation at the rim
    Float mu_o = dr::sqrt(dr::maximum((R - r) * (R + r + 2.f * ce), 0.f));
    return { cx + r * ex, cy + r * ey, mu_o };
}

/// Solid-angle density of sample_projected at the direction wo (mu_o > 0)
template <Radial law, typename Float, typename Vector3f>
Float pdf_projected(const Float &cx, const Float &cy, const Float &one_minus_c2,
                    const Float &s, const Vector3f &wo) {
    auto [c_norm, chx, chy] = centre_direction(cx, cy);
    Float kappa = direction_skew(c_norm, one_minus_c2 / (1.f + c_norm), s);
    Float dx = wo.x() - cx, dy = wo.y() - cy, r2 = dx * dx + dy * dy;
    Float r = dr::sqrt(r2);
    Mask<Float> ok = r > 0.f;
    Float inv_r = dr::select(ok, dr::rcp(r), 0.f);
    Float ex = dr::select(ok, dx * inv_r, chx), ey = dr::select(ok, dy * inv_r, chy);
    Float R = disc_exit(cx * ex + cy * ey, one_minus_c2);
    return direction_density(kappa, chx * ex + chy * ey) * radial_density<law>(r2, s) /
           radial_mass<law>(R, s) * wo.z();
}

// -------------------------------------------------- Gaussian surface lobe

/// Angle between the unit vectors a and b (stable near 0)
template <typename Vector3f> auto angle_between(const Vector3f &a, const Vector3f &b) {
    return 2.f * dr::atan2(dr::norm(a - b), dr::norm(a + b));
}

/// Angle from the direction m (m_z > 0) to the horizon along the great circle
/// whose unit tangent at m is t: pi/2 + atan2(t_z, m_z), for arguments (tz, mz)
/// proportional to (t_z, m_z) with a positive factor
template <typename Float> Float horizon_angle(const Float &tz, const Float &mz) {
    return .5f * dr::Pi<Float> + dr::atan2(tz, mz);
}

/**
 * Tangent frame of the Gaussian lobe about the mirror direction m: t1 points
 * away from the zenith (towards the nearest horizon), t2 = m x t1, and the lobe's
 * "centre" in unit-disc units: the zenith seen from m lies at angle theta_m
 * along -t1, and the horizon is about pi/2 from the zenith, so c = (theta_m /
 * (pi/2)) t1 with d = 1 - |c|.
 */
template <typename Vector3f> struct AngularFrame {
    using Float = dr::value_t<Vector3f>;
    Vector3f t1, t2;
    Float c_norm, d;

    explicit AngularFrame(const Vector3f &m) {
        Float sin_m = dr::sqrt(dr::square(m.x()) + dr::square(m.y()));
        Mask<Float> ok = sin_m > 0.f;
        Float inv = dr::select(ok, dr::rcp(sin_m), 0.f),
              hx = dr::select(ok, m.x() * inv, 1.f), hy = dr::select(ok, m.y() * inv, 0.f);
        t1 = Vector3f(m.z() * hx, m.z() * hy, -sin_m);
        t2 = Vector3f(-hy, hx, 0.f);
        Float theta_m = dr::atan2(sin_m, m.z());
        c_norm = theta_m * (2.f * dr::InvPi<Float>);
        d = 1.f - c_norm;
    }
};

/**
 * Sample the Gaussian lobe of width sigma (radians) about the mirror direction
 * m (exponential map: theta = angle to m): direction in the tangent plane from
 * sample_direction (u3, u.y), theta from a 2D Gaussian truncated at the horizon
 * along that direction (u.x).
 */
template <typename Float, typename Vector3f, typename Point2f>
Vector3f sample_angular(const Vector3f &m, const Float &sigma, const Point2f &u,
                        const Float &u3) {
    AngularFrame<Vector3f> f(m);
    Float kappa = direction_skew(f.c_norm, f.d, sigma * (2.f * dr::InvPi<Float>));
    auto [ex, ey] = sample_direction(kappa, Float(1.f), Float(0.f), u3, u.y());
    Vector3f t = f.t1 * ex + f.t2 * ey;
    Float theta_max = horizon_angle(t.z(), m.z());
    Float theta = dr::minimum(
        radial_inverse<Radial::Gaussian>(u.x() * radial_mass<Radial::Gaussian>(theta_max, sigma),
                                         sigma), theta_max);
    auto [sin_t, cos_t] = dr::sincos(theta);
    return m * cos_t + t * sin_t;
}

/// Solid-angle density of sample_angular at the direction wo (mu_o > 0)
template <typename Float, typename Vector3f>
Float pdf_angular(const Vector3f &m, const Float &sigma, const Vector3f &wo) {
    AngularFrame<Vector3f> f(m);
    Float kappa = direction_skew(f.c_norm, f.d, sigma * (2.f * dr::InvPi<Float>));
    Float theta = angle_between(wo, m);
    auto [sin_t, cos_t] = dr::sincos(theta);
    // the tangent t at m of the great circle through wo, times sin(theta)
    Vector3f ts = wo - m * cos_t;
    Float theta_max = horizon_angle(ts.z(), sin_t * m.z());
    Float a = dr::dot(ts, f.t1), b = dr::dot(ts, f.t2), n = dr::sqrt(a * a + b * b);
    Float ce_hat = dr::select(n > 0.f, a / n, 1.f);
    // dOmega = sin(theta) / theta d^2(tangent plane)
    Float jacobian = dr::select(theta < 1e-3f, 1.f + dr::square(theta) * (1.f / 6.f),
                                theta / sin_t);
    return direction_density(kappa, ce_hat) *
           radial_density<Radial::Gaussian>(dr::square(theta), sigma) /
           radial_mass<Radial::Gaussian>(theta_max, sigma) * jacobian;
}

} // namespace powder
