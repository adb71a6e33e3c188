"""BENCHMARK-ONLY: the powder model as a Python ``mi.BSDF`` subclass.

This is not the product (the C++ plugin is the one source of truth for the model); it exists
so that ``bench_python_bsdf.py`` can measure what writing the model in Python would cost. It
implements docs/model.md's L1, L2, C and the Harvey-Shack surface term for a constant albedo, a
given ``tau_o`` and an infinitely thick layer, with cosine-weighted sampling: the same values
and the same sample distribution as ``{'type': 'powder', ..., 'sampling': 'cosine'}`` (the
benchmark checks the values agree).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

RGB_NM = (611.3, 549.1, 464.3)


def _one_minus_exp_neg_over_x(x):
    """(1 - exp(-x)) / x, with its series below 1e-3 (Dr.Jit has no expm1)."""
    small = x < 1e-3
    xs = dr.select(small, 1.0, x)
    return dr.select(small, 1.0 - x * (0.5 - x / 6.0), (1.0 - dr.exp(-xs)) / xs)


def make_class() -> type:
    """The BSDF class for the current variant (``mi.BSDF`` differs per variant)."""

    class PythonPowder(mi.BSDF):
        """Properties: ``albedo`` (float), ``amplitude_volume``, ``g``, ``extinction``, ``tau_o``,
        ``amplitude_surface``, ``correlation_length``, ``wavelength`` (mono, nm)."""

        def __init__(self, props: mi.Properties):
            super().__init__(props)
            get = lambda name, default: float(props.get(name, default))  # noqa: E731
            self.rho = get("albedo", 0.8)
            self.av = get("amplitude_volume", 1.0)
            self.g = get("g", 0.0)
            self.kappa = get("extinction", 1.0)
            self.tau = get("tau_o", 2.0 / 3.0)
            self.a_s = get("amplitude_surface", 0.0)
            self.lc = get("correlation_length", 1.0)
            self.mono_nm = get("wavelength", 700.0)
            self.c0 = ((1 - self.rho) * (1 - self.rho * self.g) * 3.0) ** 0.5
            self.s0 = self.tau * float(_one_minus_exp_neg_over_x(2.0 * self.c0 * self.tau))
            flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _lambda_um(self, si):
            if mi.is_spectral:
                return si.wavelengths * 1e-3
            if mi.is_rgb:
                return mi.Color3f(*[v * 1e-3 for v in RGB_NM])
            return mi.Color1f(self.mono_nm * 1e-3) if hasattr(mi, "Color1f") else dr.full(
                mi.Spectrum, self.mono_nm * 1e-3)

        def _f(self, si, wo):
            wi = si.wi
            mu_i, mu_o = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
            valid = (mu_i > 0) & (mu_o > 0)
            mu_i, mu_o = dr.maximum(mu_i, 1e-6), dr.maximum(mu_o, 1e-6)
            rho, g, tau, c0 = self.rho, self.g, self.tau, self.c0
            cos_t = -dr.dot(wi, wo)
            l1 = rho * (1 - g * g) / dr.power(1 + g * g - 2 * g * cos_t, 1.5) / (mu_i + mu_o)
            l2 = 3 * rho * rho * (self.s0 + mu_i * mu_o / (mu_i + mu_o)) / (
                (1 + c0 * mu_i) * (1 + c0 * mu_o))
            lam = self._lambda_um(si)
            k_over = (dr.two_pi / lam) / self.kappa
            dxy = dr.sqrt(dr.square(wo.x - wi.x) + dr.square(wo.y - wi.y))
            alpha = k_over * dxy
            u = k_over * (mu_i - mu_o)
            v = 0.5 * (1 / mu_i + 1 / mu_o)
            c = dr.sqrt(c0 * c0 + alpha * alpha)
            s_c = tau * _one_minus_exp_neg_over_x(2 * c * tau)
            coh = 3 * rho * rho * (0.5 / v + s_c) / (mu_i * mu_o * (dr.square(c + v) + u * u))
            value = self.av / (4 * dr.pi) * (l1 + l2 + coh)
            if self.a_s > 0:
                fs = dr.sqrt(dr.square(wo.x + wi.x) + dr.square(wo.y + wi.y)) / lam
                value += (self.a_s * 4 * dr.pi**2 / dr.power(lam, 4) * dr.square(mu_i + mu_o)
                          * dr.pi * self.lc**2 * dr.exp(-dr.pi**2 * self.lc**2 * fs * fs))
            return dr.select(valid, value * mu_o, 0.0)

        def eval(self, ctx, si, wo, active=True):
            return self._f(si, wo) & active

        def pdf(self, ctx, si, wo, active=True):
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs = mi.BSDFSample3f()
            bs.wo = wo
            bs.pdf = self.pdf(ctx, si, wo, active)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = bs.pdf > 0
            weight = dr.select(ok, self._f(si, wo) / dr.select(ok, bs.pdf, 1.0), 0.0)
            return bs, weight & (active & ok)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return "PythonPowder[benchmark-only]"

    return PythonPowder


def register() -> None:
    """Register as ``python_powder`` in the current variant."""
    cls = make_class()
    mi.register_bsdf("python_powder", lambda props: cls(props))
