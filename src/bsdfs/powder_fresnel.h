#pragma once

/*
 * The surface term's reflectance factor (docs/model.md, "Surface reflectance factor"):
 * the unpolarised Fresnel reflectance of the smooth interface to the grain material,
 * at the cosine c = wi . h of the half vector, normalised to normal incidence, so that
 * the surface amplitude keeps its meaning at normal incidence:
 *
 *     S_F = S F(c) / F(1),   F(c) = (|r_s|^2 + |r_p|^2) / 2,   m = eta + i k,
 *     r = sqrt(m^2 - 1 + c^2),  r_s = (c - r) / (c + r),  r_p = (m^2 c - r) / (m^2 c + r).
 *
 * Written out in real arithmetic for Dr.Jit types (one value per lane and channel).
 */

#include <drjit/math.h>

namespace powder {

/// F(c) for m = eta + i k (eta > 0, k >= 0), c in [0, 1]
template <typename Value>
Value fresnel_unpolarized(const Value &c, const Value &eta, const Value &k) {
    Value re_m2 = eta * eta - k * k,   // m^2 = re_m2 + i im_m2
          im_m2 = 2.f * eta * k,
          z_re = re_m2 - 1.f + c * c,  // z = m^2 - 1 + c^2 (Im z = im_m2 >= 0)
          z_abs = dr::sqrt(z_re * z_re + im_m2 * im_m2),
          // r = sqrt(z), the root with Re r >= 0 (and Im r >= 0, as Im z >= 0)
          r_re = dr::sqrt(dr::maximum(.5f * (z_abs + z_re), 0.f)),
          r_im = dr::sqrt(dr::maximum(.5f * (z_abs - z_re), 0.f)),
          r_im2 = r_im * r_im,
          // |r_s|^2 = |c - r|^2 / |c + r|^2
          rs2 = (dr::square(c - r_re) + r_im2) /
                dr::maximum(dr::square(c + r_re) + r_im2, 1e-30f),
          // |r_p|^2 = |m^2 c - r|^2 / |m^2 c + r|^2
          p_re = re_m2 * c, p_im = im_m2 * c,
          rp2 = (dr::square(p_re - r_re) + dr::square(p_im - r_im)) /
                dr::maximum(dr::square(p_re + r_re) + dr::square(p_im + r_im), 1e-30f);
    return .5f * (rs2 + rp2);
}

/// F(1) = |m - 1|^2 / |m + 1|^2 (both polarisations agree at normal incidence)
template <typename Value>
Value fresnel_normal(const Value &eta, const Value &k) {
    return (dr::square(eta - 1.f) + k * k) / (dr::square(eta + 1.f) + k * k);
}

/// The cosine c = wi . h at the half vector h = (wi + wo) / |wi + wo| of unit vectors:
/// c = sqrt((1 + wi . wo) / 2), in [0, 1]
template <typename Value>
Value half_vector_cosine(const Value &cos_wi_wo) {
    return dr::sqrt(dr::clip(.5f * (1.f + cos_wi_wo), 0.f, 1.f));
}

} // namespace powder
