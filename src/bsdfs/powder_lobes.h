#pragma once

/*
 * Numerical helpers and importance-sampling lobes of the `powder` BSDF, as free
 * function templates over Dr.Jit types (scalar or JIT), outside the BSDF class.
 *
 * Every lobe is an exact, normalised density on the upper hemisphere, and a
 * continuous one: it is a product of two 1D laws in coordinates in which the
 * hemisphere is bounded by straight lines, each law truncated to its interval
 * and inverted in closed form. So no sample is produced below the horizon, `pdf`
 * is the density that `sample` draws from, and it has no point where its value
 * depends on the direction from which the point is approached (which a chi-square
 * test on a grid cannot integrate, see docs/powder.md, "Sampling").
 *
 *  - projected lobes (coherent cone, Harvey-Shack surface lobe) live in the
 *    projected plane (wo_x, wo_y): the unit disc cut into chords perpendicular to
 *    the direction of the lobe's centre c. First u, the coordinate along c_hat
 *    (in [-1, 1]), then v, the position along the chord (|v| <= sqrt(1 - u^2));
 *    their solid-angle density is the area density times mu_o;
 *  - the Gaussian surface lobe lives on the sphere, in the cylindrical equal-area
 *    coordinates (a, y) about the horizontal axis p perpendicular to the plane of
 *    incidence: y = wo . p in [-1, 1], a = the angle from the zenith within the
 *    plane through p and wo, in [-pi/2, pi/2]; dOmega = da dy.
 */

#include "powder_math.h"

#include <tuple>

namespace powder {

// ------------------------------------------------------------ erf_fit(x)

/**
 * erf(x) for the sampling densities: Dr.Jit's single-precision fit (dr::erf, within
 * 3.8 ulp; 1.98 ulp on [0, 1], 2.60 on [1, 4]), whose exp2 is exp2_neg here. dr::erf
 * itself uses that fit only for scalar floats: for JIT arrays it evaluates its
 * double-precision one (a degree-11 polynomial and a degree-7 rational function), far
 * more work than the sampling densities need in single precision. Above 4
 * (1 - erf < 1.6e-8, which rounds to 1) the argument is clamped at 4.
 */
template <typename T> T erf_fit(const T &x) {
    if constexpr (!dr::is_jit_v<T>) {
        return dr::erf(x);
    } else {
        T xa = dr::abs(x), x2 = dr::square(x);
        T c0 = dr::estrin(x2, 0x1.20dd74p+0f, -0x1.812672p-2f, 0x1.ce0934p-4f,
                          -0x1.b5a334p-6f, 0x1.4246b4p-8f, -0x1.273facp-11f);
        T xc = dr::minimum(xa, 4.f);
        T c1 = dr::estrin(xc, -0x1.a0d71ap+0f, -0x1.d51e3ap-1f, -0x1.3a904cp-3f,
                          0x1.1c395cp-5f, -0x1.6856bep-8f, 0x1.180f1ep-11f, -0x1.8ca9f6p-16f);
        return dr::select(xa < 1.f, x * c0, dr::copysign(1.f - exp2_neg(-c1 * xc), x));
    }
}

// ----------------------------------------------------- truncated 1D laws

/*
 * The 1D laws of the lobes, in offsets x from their centre, scale s:
 *   Gaussian: exp(-x^2 / (2 s^2)) / (s sqrt(2 pi))
 *   Cauchy:   s / (pi (x^2 + s^2))
 *   Student2: s^2 / (2 (x^2 + s^2)^(3/2))   (Student's t with 2 degrees of freedom)
 * each through G(x) = 2 F(x) - 1 (F: its distribution function), an odd function
 * with values in (-1, 1), and its inverse. Truncated to [lo, hi] with lo <= 0 <= hi:
 * an interval that holds the centre, so that G(hi) - G(lo) >= max(G(hi), -G(lo)) never
 * cancels.
 */
enum class Law { Gaussian, Cauchy, Student2 };

/// G(x) = 2 F(x) - 1 of the law of scale s
template <Law law, typename Float> Float law_g(const Float &x, const Float &s) {
    if constexpr (law == Law::Gaussian)
        return powder::erf_fit(x * (dr::InvSqrtTwo<Float> / s));
    else if constexpr (law == Law::Cauchy)
        return dr::atan2(x, s) * (2.f * dr::InvPi<Float>);
    else
        return x * dr::rsqrt(dr::square(x) + dr::square(s));
}

/// The offset x of G(x) = g, for |g| < 1 (g is clamped to 1 - 2^-24 in magnitude,
/// 5.4 widths of the Gaussian law; the callers clamp x to their interval)
template <Law law, typename Float> Float law_g_inverse(const Float &g_, const Float &s) {
    Float g = dr::clip(g_, -dr::OneMinusEpsilon<Float>, dr::OneMinusEpsilon<Float>);
    if constexpr (law == Law::Gaussian)
        return s * dr::SqrtTwo<Float> * dr::erfinv(g);
    else if constexpr (law == Law::Cauchy)
        return s * dr::tan(g * (.5f * dr::Pi<Float>));
    else
        return s * g * dr::rsqrt((1.f - g) * (1.f + g));
}

/// 2 x the density of the law of scale s at offset x (not truncated)
template <Law law, typename Float> Float law_density2(const Float &x, const Float &s) {
    if constexpr (law == Law::Gaussian) {
        return (dr::SqrtTwo<Float> * dr::InvSqrtPi<Float>) / s *
               exp_neg(.5f * dr::square(x / s));
    } else if constexpr (law == Law::Cauchy) {
        return (2.f * dr::InvPi<Float>) * s / (dr::square(x) + dr::square(s));
    } else {
        Float t = dr::square(x) + dr::square(s);
        return dr::square(s) / (t * dr::sqrt(t));
    }
}

/// Sample the law of scale s truncated to [lo, hi] (lo <= 0 <= hi) from xi in [0, 1)
template <Law law, typename Float>
Float truncated_sample(const Float &lo, const Float &hi, const Float &s, const Float &xi) {
    Float glo = law_g<law>(lo, s);
    Float x = law_g_inverse<law>(dr::fmadd(xi, law_g<law>(hi, s) - glo, glo), s);
    return dr::clip(x, lo, hi);
}

/// Density at x of the law of scale s truncated to [lo, hi] (lo <= 0 <= hi)
template <Law law, typename Float>
Float truncated_density(const Float &x, const Float &lo, const Float &hi, const Float &s) {
    return law_density2<law>(x, s) / dr::maximum(law_g<law>(hi, s) - law_g<law>(lo, s), 1e-30f);
}

/// truncated_sample on [-h, h] (G is odd: one evaluation of G)
template <Law law, typename Float>
Float truncated_sample_symmetric(const Float &h, const Float &s, const Float &xi) {
    Float x = law_g_inverse<law>(dr::fmadd(2.f, xi, -1.f) * law_g<law>(h, s), s);
    return dr::clip(x, -h, h);
}

/// truncated_density on [-h, h]
template <Law law, typename Float>
Float truncated_density_symmetric(const Float &x, const Float &h, const Float &s) {
    return law_density2<law>(x, s) / dr::maximum(2.f * law_g<law>(h, s), 1e-30f);
}

// ---------------------------------------------------------- projected lobes

/*
 * The 2D laws of the projected lobes (densities per unit area of the projected
 * plane, before truncation), scale s, r = distance to the centre c:
 *   Gaussian: exp(-r^2 / (2 s^2)) / (2 pi s^2) = Gaussian(s) in u x Gaussian(s) in v
 *   Cauchy:   s / (2 pi (r^2 + s^2)^(3/2))    = Cauchy(s) in u x Student2(sqrt(du^2 + s^2))
 *                                                in v (du = u - |c|)
 * sampled as the first law in u, truncated to the disc's extent [-1, 1], then the
 * second law in v, truncated to the chord at u, |v| <= sqrt(1 - u^2). The law in u
 * may be centred at |c| - shift (shift >= 0, towards the disc's centre) where the
 * function sampled grows inwards (projected_shift). Cut at each chord's ends, the
 * density is continuous inside the disc, and in solid angle (times mu_o) bounded.
 */
enum class Radial { Gaussian, Cauchy };

/// Unit vector from the disc centre towards c (any unit vector if c = 0)
template <typename Float>
std::tuple<Float, Float, Float> centre_direction(const Float &cx, const Float &cy) {
    Float n = dr::sqrt(cx * cx + cy * cy);
    Mask<Float> ok = n > 0.f;
    Float inv = dr::select(ok, dr::rcp(n), 0.f);
    return { n, dr::select(ok, cx * inv, 1.f), dr::select(ok, cy * inv, 0.f) };
}

/// The law in v of the chord lobe and its scale, at du = u - |c|
template <Radial law, typename Float> Float chord_scale(const Float &du, const Float &s) {
    if constexpr (law == Radial::Gaussian) {
        DRJIT_MARK_USED(du);
        return s;
    } else {
        return dr::sqrt(dr::square(du) + dr::square(s));
    }
}
template <Radial law> constexpr Law law_u = law == Radial::Gaussian ? Law::Gaussian : Law::Cauchy;
template <Radial law> constexpr Law law_v = law == Radial::Gaussian ? Law::Gaussian : Law::Student2;

/**
 * Shift of the Gaussian chord lobe of the Harvey-Shack term towards the disc's centre:
 * S cos(theta_o) dOmega = S dA, and S has the factor (mu_i + mu_o)^2, which grows
 * inwards (steeply near the rim: mu_o = sqrt(1 - u^2)). A Gaussian in u times
 * exp(beta u) is a Gaussian of the same width centred beta s^2 further on, so the
 * centre moves by s^2 times the slope of log (mu_i + mu_o)^2 in u, 2 u / (mu_o (mu_i +
 * mu_o)), taken one width inside the centre (u = |c| - s), and at most by 2 s (and |c|).
 */
template <typename Float>
Float projected_shift(const Float &c_norm, const Float &mu_c, const Float &s) {
    Float u = dr::maximum(c_norm - s, 0.f), mu = dr::sqrt((1.f - u) * (1.f + u));
    Float shift = 2.f * dr::square(s) * u / (mu * (mu_c + mu));
    return dr::minimum(shift, dr::minimum(2.f * s, c_norm));
}

/**
 * Sample the projected lobe of scale s centred on the point c = (cx, cy) of the unit
 * disc, with one_minus_c2 = 1 - |c|^2 (= mu^2 for c = +-wi_xy, passed exactly), its
 * law in u centred at |c| - shift: u from u.x, v from u.y. Returns the direction
 * (mu_o >= 0).
 */
template <Radial law, typename Float, typename Point2f>
dr::Array<Float, 3> sample_projected(const Float &cx, const Float &cy,
                                     const Float &one_minus_c2, const Float &s,
                                     const Float &shift, const Point2f &u) {
    auto [c_norm, chx, chy] = centre_direction(cx, cy);
    // offsets x = u - (|c| - shift) lie in [lo, hi]; hi - x = 1 - u without cancellation
    Float hi = one_minus_c2 / (1.f + c_norm) + shift, lo = shift - (1.f + c_norm);
    Float x = truncated_sample<law_u<law>>(lo, hi, s, u.x());
    // (w may exceed 2 = hi - lo by a rounding error)
    Float w = hi - x, h = dr::sqrt(dr::maximum(w * (2.f - w), 0.f)), du = x - shift;
    Float sv = chord_scale<law>(du, s);
    Float v = truncated_sample_symmetric<law_v<law>>(h, sv, u.y());
    Float mu_o = dr::sqrt(dr::maximum((h - v) * (h + v), 0.f));
    return { cx + du * chx - v * chy, cy + du * chy + v * chx, mu_o };
}

/// Solid-angle density of sample_projected at the direction wo (mu_o > 0)
template <Radial law, typename Float, typename Vector3f>
Float pdf_projected(const Float &cx, const Float &cy, const Float &one_minus_c2,
                    const Float &s, const Float &shift, const Vector3f &wo) {
    auto [c_norm, chx, chy] = centre_direction(cx, cy);
    Float hi = one_minus_c2 / (1.f + c_norm) + shift, lo = shift - (1.f + c_norm);
    Float dx = wo.x() - cx, dy = wo.y() - cy;
    Float du = dx * chx + dy * chy, v = dy * chx - dx * chy;
    Float h = dr::sqrt(dr::square(wo.z()) + dr::square(v)); // 1 - u^2 = mu_o^2 + v^2
    Float mass = dr::maximum(law_g<law_u<law>>(hi, s) - law_g<law_u<law>>(lo, s), 1e-30f);
    if constexpr (law == Radial::Gaussian) {
        // the two Gaussian densities of truncated_density with one exponential
        Float inv_s2 = dr::rcp(dr::square(s)),
              dens = (2.f * dr::InvPi<Float>) * inv_s2 *
                     exp_neg(.5f * (dr::square(du + shift) + dr::square(v)) * inv_s2);
        return dens / (mass * dr::maximum(2.f * law_g<Law::Gaussian>(h, s), 1e-30f)) * wo.z();
    } else {
        Float sv = chord_scale<law>(du, s);
        return law_density2<Law::Cauchy>(du, s) / mass *
               truncated_density_symmetric<Law::Student2>(v, h, sv) * wo.z();
    }
}

// -------------------------------------------------- Gaussian surface lobe

/// Angle between the unit vectors a and b (stable near 0)
template <typename Vector3f> auto angle_between(const Vector3f &a, const Vector3f &b) {
    return 2.f * dr::atan2(dr::norm(a - b), dr::norm(a + b));
}

/**
 * Coordinates of the Gaussian lobe about the mirror direction m (m_z > 0): the
 * horizontal unit vector h towards m's azimuth, p = z x h, and the law of the angle a
 * (from the zenith, towards h) in offsets x = (hi - b) where b = pi/2 - a is the
 * elevation within the plane through p and wo: b in [0, pi], x in [hi - pi, hi]. The
 * law is centred at a = theta_m - shift, theta_m = m's zenith angle: eval has the
 * factor mu_o = cos(a) sqrt(1 - y^2), so the centre moves towards the zenith by
 * sigma^2 times the slope of -log cos(a), tan(a), one width inside (a = theta_m - sigma),
 * at most 2 sigma (and theta_m).
 */
template <typename Vector3f> struct CylinderFrame {
    using Float = dr::value_t<Vector3f>;
    Float hx, hy, hi;

    CylinderFrame(const Vector3f &m, const Float &sigma) {
        Float sin_m = dr::sqrt(dr::square(m.x()) + dr::square(m.y()));
        Mask<Float> ok = sin_m > 0.f;
        Float inv = dr::select(ok, dr::rcp(sin_m), 0.f);
        hx = dr::select(ok, m.x() * inv, 1.f);
        hy = dr::select(ok, m.y() * inv, 0.f);
        Float theta_m = dr::atan2(sin_m, m.z()), elevation = dr::atan2(m.z(), sin_m);
        auto [sin_t, cos_t] = dr::sincos(dr::maximum(theta_m - sigma, 0.f));
        Float shift = dr::minimum(dr::square(sigma) * sin_t / cos_t,
                                  dr::minimum(2.f * sigma, theta_m));
        hi = elevation + shift;
    }
};

/**
 * Sample the Gaussian lobe of width sigma (radians) about the mirror direction m:
 * y = wo . p from a Gaussian of width sigma truncated to [-1, 1] (u.x), then the angle
 * a from a Gaussian of width sigma / sqrt(1 - y^2) (the same angle on the sphere)
 * truncated to [-pi/2, pi/2] (u.y). Near the poles +-p the law of a becomes uniform,
 * so the density stays continuous there.
 */
template <typename Float, typename Vector3f, typename Point2f>
Vector3f sample_angular(const Vector3f &m, const Float &sigma, const Point2f &u) {
    CylinderFrame<Vector3f> f(m, sigma);
    Float y = truncated_sample_symmetric<Law::Gaussian>(Float(1.f), sigma, u.x());
    Float cy = dr::sqrt((1.f - y) * (1.f + y));
    // (at y = +-1 the direction is +-p whatever a is)
    Float x = truncated_sample<Law::Gaussian>(f.hi - dr::Pi<Float>, f.hi,
                                              sigma / dr::maximum(cy, 1e-30f), u.y());
    auto [sin_b, cos_b] = dr::sincos(f.hi - x);
    Float r = cy * cos_b;
    return Vector3f(r * f.hx - y * f.hy, r * f.hy + y * f.hx, cy * sin_b);
}

/// Solid-angle density of sample_angular at the direction wo (mu_o > 0)
template <typename Float, typename Vector3f>
Float pdf_angular(const Vector3f &m, const Float &sigma, const Vector3f &wo) {
    CylinderFrame<Vector3f> f(m, sigma);
    Float y = wo.y() * f.hx - wo.x() * f.hy, r = wo.x() * f.hx + wo.y() * f.hy;
    Float cy = dr::sqrt(dr::square(r) + dr::square(wo.z()));
    Float x = f.hi - dr::atan2(wo.z(), r);
    return truncated_density_symmetric<Law::Gaussian>(y, Float(1.f), sigma) *
           truncated_density<Law::Gaussian>(x, f.hi - dr::Pi<Float>, f.hi,
                                             sigma / dr::maximum(cy, 1e-30f));
}

} // namespace powder
