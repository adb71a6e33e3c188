#pragma once

/*
 * exp(-x) and 1 - exp(-x) for the `powder` BSDF, as function templates over Dr.Jit
 * types (scalar or JIT): the exponentials of eval (the model's terms) and of the
 * sampling densities.
 */

#include <drjit/math.h>

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
 * of dr::exp2 at the same argument (tests/plugin/test_fast_paths.py), in 19 operations of the
 * LLVM kernel where dr::exp takes 22 (it also handles overflow, which these arguments
 * cannot reach). Scalar variants, and
 * arguments that carry gradients (Dr.Jit's exact derivative rule), call dr::exp2.
 *
 * t > ExpNegCut2 gives 0 in every variant. These values are always multiplied by a
 * prefactor, and the products can be denormal floats (below 1.2e-38), which are
 * slow to compute with on many CPUs: returning 0 rather than a tiny power of two
 * keeps them out of the kernels. A term below 5.4e-20 of its prefactor is far below
 * the float resolution of any sum it enters.
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

} // namespace powder
