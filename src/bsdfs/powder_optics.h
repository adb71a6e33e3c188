#pragma once

/*
 * Grain optics for the `powder` BSDF, in double precision and scalar code
 * (evaluated once per parameter change, never per BSDF sample):
 *
 *  - optical constants n + i k against wavelength (powder_optical_constants.h);
 *  - Lorenz-Mie extinction and scattering efficiencies of a sphere
 *    (Bohren & Huffman, with downward recurrences for the logarithmic
 *    derivatives D_n(mx) and D_n(x));
 *  - the extrapolation ratio tau_o from the Fresnel reflectance of the grain
 *    material (Zhu, Pine & Weitz 1991, docs/model.md);
 *  - the grain models (docs/model.md, "Grain models"): isolated spheres, agglomerates
 *    of crystallites (Bruggeman or Maxwell Garnett effective index) and Hapke's
 *    equivalent slab;
 *  - the albedo table over wavelength of one or two grain populations (docs/model.md,
 *    "Single-scattering albedo rho from the grains"), with the derivatives of rho
 *    with respect to the fittable grain parameters, rows spread over a caller's
 *    parallel-for.
 */

#include <algorithm>
#include <array>
#include <cmath>
#include <complex>
#include <exception>
#include <mutex>
#include <fstream>
#include <sstream>
#include <string>
#include <stdexcept>
#include <utility>
#include <vector>

#include "powder_optical_constants.h"
#include "powder_registry.h"

/* Self-contained (no Mitsuba headers): the plugin includes it, and so does the
   Python module mitsuba_powder._optics, which exposes the same double-precision
   code to Python (tests against miepython, colour helper). */
namespace powder {

/**
 * The albedo of two grain populations of radii r1, r2, the second at volume fraction f2
 * (docs/model.md, "Single-scattering albedo rho from the grains"): rho = sum_j (f_j / r_j)
 * Q_sca,j / sum_j (f_j / r_j) Q_ext,j. Generic: doubles here, and per lane and channel
 * in the plugin's spatially varying grains.
 */
template <typename Q, typename R>
Q population_mix(const Q &q_ext1, const Q &q_sca1, const R &r1, const Q &q_ext2,
                 const Q &q_sca2, const R &r2, const R &f2) {
    R w1 = (1.f - f2) / r1, w2 = f2 / r2;
    return (w1 * q_sca1 + w2 * q_sca2) / (w1 * q_ext1 + w2 * q_ext2);
}

struct MieEfficiencies { double q_ext, q_sca; };

/**
 * Extinction and scattering efficiencies of a homogeneous sphere of relative
 * complex index m = n + i k (k >= 0 absorbs) and size parameter x = 2 pi r / lambda.
 *
 * Bohren & Huffman's series with n_stop = x + 4 x^(1/3) + 2 terms: the
 * logarithmic derivative D_n(mx) by downward recurrence started
 * 16 + 8 |mx|^(1/3) orders above max(n_stop, |mx|) (BHMIE's fixed 15 orders leave
 * errors of 5e-4 at |mx| ~ 300; 4 |mx|^(1/3) is the least found to reach 1e-7),
 * the Riccati-Bessel functions psi_n(x), chi_n(x) by upward recurrence (stable
 * up to n_stop, and regular at x = k pi, where a ratio form psi_n = psi_{n-1} /
 * (D_n(x) + n / x) breaks down). Agrees with miepython to < 1e-7 relative for x in
 * [1e-3, 200].
 */
inline MieEfficiencies mie_efficiencies(std::complex<double> m, double x) {
    using C = std::complex<double>;
    int n_stop = (int) (x + 4.0 * std::cbrt(x) + 2.0);
    C mx = m * x;
    int n_mx = (int) (std::max((double) n_stop, std::abs(mx)) + 16.0 +
                      8.0 * std::cbrt(std::abs(mx)));
    std::vector<C> d(n_mx + 1, C(0.0));
    for (int n = n_mx; n > 0; --n)
        d[n - 1] = (double) n / mx - 1.0 / (d[n] + (double) n / mx);
    double psi_prev2 = std::cos(x), psi_prev = std::sin(x),
           chi_prev2 = -std::sin(x), chi_prev = std::cos(x);
    C xi_prev(psi_prev, -chi_prev);
    double q_ext = 0.0, q_sca = 0.0;
    for (int n = 1; n <= n_stop; ++n) {
        double f = (2.0 * n - 1.0) / x,
               psi = f * psi_prev - psi_prev2,
               chi = f * chi_prev - chi_prev2;
        C xi(psi, -chi);
        C t = d[n] / m + n / x;
        C a = (t * psi - psi_prev) / (t * xi - xi_prev);
        t = m * d[n] + n / x;
        C b = (t * psi - psi_prev) / (t * xi - xi_prev);
        q_sca += (2.0 * n + 1.0) * (std::norm(a) + std::norm(b));
        q_ext += (2.0 * n + 1.0) * (a + b).real();
        psi_prev2 = psi_prev;
        psi_prev = psi;
        chi_prev2 = chi_prev;
        chi_prev = chi;
        xi_prev = C(psi_prev, -chi_prev);
    }
    return { 2.0 * q_ext / (x * x), 2.0 * q_sca / (x * x) };
}

/// Unpolarised Fresnel reflectance inside a medium of index n at cos(theta) = mu,
/// towards air (total internal reflection above the critical angle)
inline double fresnel_internal(double n, double mu) {
    double sin2 = std::max(0.0, 1.0 - mu * mu), s2t = n * n * sin2;
    if (s2t >= 1.0)
        return 1.0;
    double mu_t = std::sqrt(1.0 - s2t);
    double rs = (n * mu - mu_t) / (n * mu + mu_t), rp = (mu - n * mu_t) / (mu + n * mu_t);
    return 0.5 * (rs * rs + rp * rp);
}

/**
 * tau_o = (2/3) (1 + Rbar) / (1 - Rbar), Rbar = (3 C2 + 2 C1) / (3 C2 - 2 C1 + 2),
 * C_j = int_0^1 R(mu) mu^j dmu (docs/model.md, corrected sign). The total-reflection
 * part is integrated exactly; the rest with Simpson's rule in t, where
 * mu = mu_c + (1 - mu_c) t^2 removes the square-root kink at the critical angle.
 */
inline double tau_o_fresnel(double n) {
    double mu_c = n > 1.0 ? std::sqrt(1.0 - 1.0 / (n * n)) : 0.0;
    double c1 = 0.5 * mu_c * mu_c, c2 = mu_c * mu_c * mu_c / 3.0;
    const int steps = 2000; // even
    double s1 = 0.0, s2 = 0.0;
    for (int i = 0; i <= steps; ++i) {
        double t = (double) i / steps, mu = mu_c + (1.0 - mu_c) * t * t,
               jac = 2.0 * (1.0 - mu_c) * t,
               w = (i == 0 || i == steps) ? 1.0 : (i % 2 ? 4.0 : 2.0),
               f = fresnel_internal(n, mu) * jac * w;
        s1 += f * mu;
        s2 += f * mu * mu;
    }
    c1 += s1 / (3.0 * steps);
    c2 += s2 / (3.0 * steps);
    double r = (3.0 * c2 + 2.0 * c1) / (3.0 * c2 - 2.0 * c1 + 2.0);
    return (2.0 / 3.0) * (1.0 + r) / (1.0 - r);
}

// ------------------------------------------------------------ grain models

/// What scatters in the powder (docs/model.md, "Grain models"): isolated Mie spheres,
/// agglomerates of crystallites (effective medium), or Hapke's equivalent slab
enum class GrainModel { Sphere, Agglomerate, Slab };

/// Effective-medium rule of an agglomerate
enum class Mixing { Bruggeman, MaxwellGarnett };

/**
 * Effective index sqrt(eps) of crystallites of index m at volume fill f in air.
 * Bruggeman: the root of 2 eps^2 - b eps - eps_i = 0, b = (3 f - 1) eps_i + (2 - 3 f),
 * with Im(eps) >= 0 (for a real eps_i the roots are real and of opposite signs: the
 * positive one). Maxwell Garnett: eps = (1 + 2 f beta) / (1 - f beta),
 * beta = (eps_i - 1) / (eps_i + 2). The principal square root has Re >= 0, Im >= 0.
 */
inline std::complex<double> effective_index(std::complex<double> m, double f, Mixing mixing) {
    using C = std::complex<double>;
    C eps_i = m * m, eps;
    if (mixing == Mixing::Bruggeman) {
        C b = (3.0 * f - 1.0) * eps_i + (2.0 - 3.0 * f),
          d = std::sqrt(b * b + 8.0 * eps_i),
          e1 = (b + d) / 4.0, e2 = (b - d) / 4.0;
        // the physical root: larger Im (absorbing medium); for (nearly) real roots,
        // which differ in sign, the larger real part
        double tol = 1e-12 * (std::abs(e1) + std::abs(e2));
        if (std::abs(e1.imag() - e2.imag()) <= tol)
            eps = e1.real() >= e2.real() ? e1 : e2;
        else
            eps = e1.imag() > e2.imag() ? e1 : e2;
    } else {
        C beta = (eps_i - 1.0) / (eps_i + 2.0);
        eps = (1.0 + 2.0 * f * beta) / (1.0 - f * beta);
    }
    return std::sqrt(eps);
}

/**
 * The Bruggeman effective index sqrt(eps) of a mixture of materials of indices m_j at volume
 * fractions f_j (summing to 1; docs/model.md, "The mixture's index for tau_o"): the root
 * with Im(eps) >= 0 of sum_j f_j (eps_j - eps) / (eps_j + 2 eps) = 0, eps_j = m_j^2, by
 * Newton's method from the volume average of the eps_j. One distinct index (or one fraction
 * of 1) returns it exactly.
 */
inline std::complex<double> bruggeman_mixture(const std::vector<std::complex<double>> &m,
                                              const std::vector<double> &f) {
    using C = std::complex<double>;
    std::vector<C> e;
    std::vector<double> w;
    for (size_t j = 0; j < m.size(); ++j) { // distinct materials with a positive fraction
        if (!(f[j] > 0.0))
            continue;
        size_t i = 0;
        while (i < e.size() && e[i] != m[j] * m[j])
            ++i;
        if (i == e.size()) {
            e.push_back(m[j] * m[j]);
            w.push_back(0.0);
        }
        w[i] += f[j];
    }
    if (e.size() == 1)
        for (size_t j = 0; j < m.size(); ++j)
            if (f[j] > 0.0)
                return m[j];
    if (e.empty())
        fail("powder: the fractions of the grain populations are all 0");
    C eps(0.0);
    double total = 0.0;
    for (size_t i = 0; i < e.size(); ++i) {
        eps += w[i] * e[i];
        total += w[i];
    }
    eps /= total;
    for (int it = 0; it < 200; ++it) {
        C F(0.0), dF(0.0);
        for (size_t i = 0; i < e.size(); ++i) {
            C d = e[i] + 2.0 * eps;
            F += w[i] * (e[i] - eps) / d;
            dF += w[i] * (-3.0 * e[i]) / (d * d);
        }
        C step = F / dF;
        eps -= step;
        if (eps.imag() < 0.0)
            eps = C(eps.real(), 0.0);
        if (std::abs(step) <= 1e-14 * std::abs(eps))
            return std::sqrt(eps);
    }
    fail("powder: the Bruggeman index of the grain mixture did not converge");
}

/// Hapke's equivalent-slab albedo and its derivative with respect to the grain
/// size D (um) for index m = n + ik (n > 1) at wavelength wl_um (docs/model.md)
inline std::pair<double, double> slab_albedo(std::complex<double> m, double d_um,
                                             double wl_um) {
    const double pi = 3.14159265358979323846;
    double n = m.real(), k = m.imag();
    double r0 = ((n - 1.0) * (n - 1.0) + k * k) / ((n + 1.0) * (n + 1.0) + k * k),
           s_e = 0.0587 + 0.8543 * r0 + 0.0870 * r0 * r0,
           s_i = 1.0 - (0.9413 - 0.8543 * r0 - 0.0870 * r0 * r0) / n,
           path = (2.0 / 3.0) * (n * n - (1.0 / n) * std::pow(n * n - 1.0, 1.5)), // <D> / D
           alpha = 4.0 * pi * k / wl_um,
           theta = std::exp(-alpha * path * d_um),
           denom = 1.0 - s_i * theta,
           rho = s_e + (1.0 - s_e) * (1.0 - s_i) * theta / denom,
           d_theta = -alpha * path * theta,
           d_rho = (1.0 - s_e) * (1.0 - s_i) / (denom * denom) * d_theta;
    return { rho, d_rho };
}

// ------------------------------------------------------------ albedo table

/// The grains (docs/model.md): `populations` populations (1..4) of radii r[j] (um) and
/// volume fractions f[j] of the solid, f[j] for j >= 1 given and f[0] = 1 - the others;
/// for agglomerates (one population) their radius (um), fill and mixing rule (r[0] is then
/// the crystallite radius, which does not enter the albedo)
struct Grains {
    static constexpr size_t Max = powder_param::MaxPopulations;
    std::array<double, Max> r{ 1.0, 1.0, 1.0, 1.0 }, f{ 1.0, 0.0, 0.0, 0.0 };
    size_t populations = 1;
    GrainModel model = GrainModel::Sphere;
    double agglomerate_radius = 1.0, agglomerate_fill = 0.5;
    Mixing mixing = Mixing::Bruggeman;

    /// Set the fractions of populations 2..n; population 1 gets 1 - their sum
    void set_fractions(const std::array<double, Max> &given) {
        f[0] = 1.0;
        for (size_t j = 1; j < Max; ++j) {
            f[j] = j < populations ? given[j] : 0.0;
            f[0] -= f[j];
        }
        f[0] = std::max(f[0], 0.0); // (a sum above 1 by rounding)
    }
};

/// The grain index of each population at one wavelength
using PopulationIndex = std::array<std::complex<double>, powder_param::MaxPopulations>;

/// One wavelength of the albedo table: rho = sum_j (f_j / r_j) Q_sca,j / sum_j
/// (f_j / r_j) Q_ext,j, its derivatives with respect to the fittable grain parameters
/// (indexed by powder_param::Id; zero unless requested, or for a parameter not in use),
/// and the efficiencies of each population (agglomerates: of the agglomerate; slab:
/// Q_ext = 1, Q_sca = rho of the slab)
struct AlbedoRow {
    double rho = 0.0;
    std::array<double, powder_param::Count> d{};
    std::array<double, powder_param::MaxPopulations> q_ext{}, q_sca{};
};
/// (Q_ext, Q_sca, dQ_ext/dr, dQ_sca/dr) of Mie spheres of radius r (um) and index m
/// at wl_nm; the derivatives (only with `derivatives`) by a forward difference in x
/// of relative step 1e-6 (truncation error ~1e-5 relative, far below what fitting
/// needs). Throws if the size parameter leaves [1e-3, 200]; `name` is the property.
inline std::array<double, 4> population_efficiencies(double r, double wl_nm,
                                                     std::complex<double> m,
                                                     const char *name, bool derivatives) {
    const double pi = 3.14159265358979323846;
    double x = 2.0 * pi * r / (wl_nm * 1e-3);
    // (a relative slack of 1e-6 absorbs the float rounding of r)
    if (!(x >= 1e-3 * (1.0 - 1e-6) && x <= 200.0 * (1.0 + 1e-6)))
        fail("powder: property \"", name, "\" = ", r, " um gives the size parameter "
             "2 pi r / lambda = ", x, " at ", wl_nm, " nm; valid range is [1e-3, 200] "
             "(radius ", 1e-3 * wl_nm * 1e-3 / (2.0 * pi), "-",
             200.0 * wl_nm * 1e-3 / (2.0 * pi), " um at this wavelength)");
    MieEfficiencies q = mie_efficiencies(m, x);
    if (!(q.q_ext > 0.0))
        fail("powder: grains of index ", m.real(), " + ", m.imag(),
             "i do not interact with light (Q_ext = 0)");
    std::array<double, 4> out{ q.q_ext, q.q_sca, 0.0, 0.0 };
    if (derivatives) {
        const double h = 1e-6;
        MieEfficiencies qp = mie_efficiencies(m, x * (1.0 + h));
        double s = 1.0 / (h * r); // dQ/dr = dQ/dx * x / r
        out[2] = (qp.q_ext - q.q_ext) * s;
        out[3] = (qp.q_sca - q.q_sca) * s;
    }
    return out;
}

/// Slab grains need a real index above 1 at every wavelength they are evaluated at
inline void check_slab_index(std::complex<double> m, double wl_nm) {
    if (!(m.real() > 1.0))
        fail("powder: grains = \"slab\" needs the real index of the grain material above 1 "
             "(Hapke's equivalent slab), but it is n = ", m.real(), " at ", wl_nm,
             " nm (property \"eta\" or \"material\"); valid range is (1, inf); use "
             "grains = \"sphere\" for this material");
}

/// One population of radius r (um): Mie spheres, or for `slab` grains of size
/// D = 2 r with Q_ext = 1 and Q_sca = rho of Hapke's slab (docs/model.md); as
/// population_efficiencies (the slab's derivative is analytic)
inline std::array<double, 4> population(const Grains &g, double r, double wl_nm,
                                        std::complex<double> m, const char *name,
                                        bool derivatives) {
    if (g.model == GrainModel::Slab) {
        auto [rho, d_rho_d] = slab_albedo(m, 2.0 * r, wl_nm * 1e-3);
        return { 1.0, rho, 0.0, derivatives ? 2.0 * d_rho_d : 0.0 };
    }
    return population_efficiencies(r, wl_nm, m, name, derivatives);
}

/// Agglomerates (one population): Mie spheres of radius agglomerate_radius and the
/// effective index of the packed crystallites. d rho / d fill by a difference of
/// step 1e-6 in the fill (backwards at fill = 1)
inline AlbedoRow agglomerate_row(const Grains &g, double wl_nm, std::complex<double> m,
                                 bool derivatives) {
    AlbedoRow row;
    double fill = g.agglomerate_fill, ra = g.agglomerate_radius;
    auto a = population_efficiencies(ra, wl_nm, effective_index(m, fill, g.mixing),
                                     "agglomerate_radius", derivatives);
    row.q_ext[0] = a[0];
    row.q_sca[0] = a[1];
    row.rho = a[1] / a[0];
    if (derivatives) {
        row.d[powder_param::AgglomerateRadius] = (a[3] - row.rho * a[2]) / a[0];
        const double h = 1e-6;
        double fill2 = fill + h <= 1.0 ? fill + h : fill - h;
        auto b = population_efficiencies(ra, wl_nm, effective_index(m, fill2, g.mixing),
                                         "agglomerate_radius", false);
        row.d[powder_param::AgglomerateFill] = (b[1] / b[0] - row.rho) / (fill2 - fill);
    }
    return row;
}

/// The albedo table row at one wavelength (nm) for the grain index m[j] of each population
inline AlbedoRow albedo_row(const Grains &g, double wl_nm, const PopulationIndex &m,
                            bool derivatives) {
    if (g.model == GrainModel::Agglomerate)
        return agglomerate_row(g, wl_nm, m[0], derivatives);
    AlbedoRow row;
    // N = sum_j (f_j / r_j) Q_sca,j, D = sum_j (f_j / r_j) Q_ext,j, rho = N / D; with
    // f_1 = 1 - sum_{j>=2} f_j: dN/df_j = Q_sca,j / r_j - Q_sca,1 / r_1 (and D alike)
    std::array<std::array<double, 4>, Grains::Max> q{};
    double num = 0.0, den = 0.0;
    for (size_t j = 0; j < g.populations; ++j) {
        if (g.model == GrainModel::Slab)
            check_slab_index(m[j], wl_nm);
        q[j] = population(g, g.r[j], wl_nm, m[j],
                          powder_param::Table[powder_param::PopulationRadius[j]].name,
                          derivatives);
        num += g.f[j] / g.r[j] * q[j][1];
        den += g.f[j] / g.r[j] * q[j][0];
        row.q_ext[j] = q[j][0];
        row.q_sca[j] = q[j][1];
    }
    row.rho = g.populations == 1 ? q[0][1] / q[0][0] : num / den;
    if (derivatives) {
        for (size_t j = 0; j < g.populations; ++j) {
            double r = g.r[j], f = g.f[j];
            double dn = f * (q[j][3] / r - q[j][1] / (r * r)),
                   dd = f * (q[j][2] / r - q[j][0] / (r * r));
            row.d[powder_param::PopulationRadius[j]] = (dn - row.rho * dd) / den;
            if (j == 0)
                continue; // (one population: no fraction, not a difference of rounding errors)
            dn = q[j][1] / r - q[0][1] / g.r[0];
            dd = q[j][0] / r - q[0][0] / g.r[0];
            row.d[powder_param::PopulationFraction[j]] = (dn - row.rho * dd) / den;
        }
    }
    return row;
}

/// Size parameter 2 pi r |n + ik| / lambda of crystallites of radius r (um) at each
/// wavelength (nm): a mixing rule holds below about 0.5
inline std::vector<double> crystallite_size_parameters(
    double r, const std::vector<double> &wl_nm,
    const std::vector<std::complex<double>> &index) {
    const double pi = 3.14159265358979323846;
    std::vector<double> x(wl_nm.size());
    for (size_t i = 0; i < wl_nm.size(); ++i)
        x[i] = 2.0 * pi * r * std::abs(index[i]) / (wl_nm[i] * 1e-3);
    return x;
}


/// Runs f(i) for i in [0, n) on the calling thread
struct SerialFor {
    template <typename F> void operator()(size_t n, F &&f) const {
        for (size_t i = 0; i < n; ++i)
            f(i);
    }
};

/// Runs row(i) for i in [0, n) through parallel_for (rows may run on several
/// threads) and rethrows here the first exception any row threw
template <typename ParallelFor, typename Row>
void for_each_row(size_t n, ParallelFor &&parallel_for, Row &&row) {
    std::exception_ptr error;
    std::mutex error_mutex;
    parallel_for(n, [&](size_t i) {
        try {
            row(i);
        } catch (...) {
            std::lock_guard<std::mutex> lock(error_mutex);
            if (!error)
                error = std::current_exception();
        }
    });
    if (error)
        std::rethrow_exception(error);
}

/**
 * The albedo table at the wavelengths wl_nm (grain index `index` at each).
 * Rows are independent: parallel_for(n, row) may run them on several threads
 * (the plugin passes Dr.Jit's thread pool); the first exception of any row is
 * rethrown here.
 */
template <typename ParallelFor = SerialFor>
std::vector<AlbedoRow> albedo_table(const Grains &g, const std::vector<double> &wl_nm,
                                    const std::vector<PopulationIndex> &index,
                                    bool derivatives,
                                    ParallelFor &&parallel_for = ParallelFor()) {
    std::vector<AlbedoRow> rows(wl_nm.size());
    for_each_row(rows.size(), parallel_for, [&](size_t i) {
        rows[i] = albedo_row(g, wl_nm[i], index[i], derivatives);
    });
    return rows;
}

/// The variable an efficiency table is regular in: u = ln(r / um) of a grain radius,
/// or u = the fill of agglomerates (at the agglomerate radius of the Grains)
enum class TableAxis { LogRadius, Fill };

/**
 * Efficiency tables of spatially varying grains (a texture-valued radius, or the
 * fill of agglomerates): for each wavelength i and node j of a regular grid in u
 * (TableAxis), records of 8 values (Q_ext, Q_sca, dQ_ext/du, dQ_sca/du at node j,
 * then the same at node j + 1), so that one packet gather gives what cubic Hermite
 * interpolation in u needs (the node spacing: efficiency_table).
 */
struct EfficiencyTable {
    TableAxis axis = TableAxis::LogRadius;
    double u0 = 0.0, du = 1.0; ///< u of node 0, spacing
    size_t nodes = 0;
    std::vector<double> records; ///< (wavelength i, node j) -> 8 values at 8 (i nodes + j)
};

/// (Q_ext, Q_sca, dQ_ext/dfill, dQ_sca/dfill) of agglomerates of radius
/// g.agglomerate_radius and fill `fill` in (0, 1]; the derivatives (only with
/// `derivatives`) by a central difference of step 1e-5 in the fill (one-sided at 1)
inline std::array<double, 4> fill_population(const Grains &g, double fill, double wl_nm,
                                             std::complex<double> m, bool derivatives) {
    auto at = [&](double f) {
        return population_efficiencies(g.agglomerate_radius, wl_nm,
                                       effective_index(m, f, g.mixing), "agglomerate_radius",
                                       false);
    };
    auto a = at(fill);
    if (!derivatives)
        return { a[0], a[1], 0.0, 0.0 };
    const double h = 1e-5;
    double lo = std::max(fill - h, 0.5 * fill), hi = std::min(fill + h, 1.0);
    auto b = at(lo), c = at(hi);
    return { a[0], a[1], (c[0] - b[0]) / (hi - lo), (c[1] - b[1]) / (hi - lo) };
}

/// Efficiencies of one population at the table variable v (the radius r in um, or
/// the fill) and dQ/du: Mie spheres (index m, or the effective index of
/// agglomerates), or the slab
inline std::array<double, 4> table_point(const Grains &g, TableAxis axis, double v,
                                         double wl_nm, std::complex<double> m,
                                         const char *name, bool derivatives = true);

/// Efficiencies of one population of radius r (um) for the texture tables: Mie
/// spheres (index m, or the effective index of agglomerates), or the slab
inline std::array<double, 4> table_population(const Grains &g, double r, double wl_nm,
                                              std::complex<double> m, const char *name) {
    if (g.model == GrainModel::Agglomerate)
        return population_efficiencies(r, wl_nm,
                                       effective_index(m, g.agglomerate_fill, g.mixing), name,
                                       true);
    if (g.model == GrainModel::Slab)
        check_slab_index(m, wl_nm);
    return population(g, r, wl_nm, m, name, true);
}

inline std::array<double, 4> table_point(const Grains &g, TableAxis axis, double v,
                                         double wl_nm, std::complex<double> m,
                                         const char *name, bool derivatives) {
    if (axis == TableAxis::Fill)
        return fill_population(g, v, wl_nm, m, derivatives);
    auto a = table_population(g, v, wl_nm, m, name);
    return { a[0], a[1], a[2] * v, a[3] * v }; // dQ/du = r dQ/dr
}

/// The table variable (radius in um, or fill) at u
inline double table_value(TableAxis axis, double u) {
    return axis == TableAxis::Fill ? u : std::exp(u);
}

/// Records of an efficiency table with node spacing du from u0 (nodes nodes)
template <typename ParallelFor>
void fill_efficiency_table(EfficiencyTable &t, const Grains &g,
                           const std::vector<double> &wl_nm,
                           const std::vector<std::complex<double>> &index, const char *name,
                           ParallelFor &parallel_for) {
    t.records.assign(wl_nm.size() * t.nodes * 8, 0.0);
    std::vector<double> q(wl_nm.size() * t.nodes * 4);
    for_each_row(wl_nm.size(), parallel_for, [&](size_t i) {
        for (size_t j = 0; j < t.nodes; ++j) {
            double v = table_value(t.axis, t.u0 + (double) j * t.du);
            auto a = table_point(g, t.axis, v, wl_nm[i], index[i], name);
            std::copy(a.begin(), a.end(), &q[(i * t.nodes + j) * 4]);
        }
    });
    for (size_t i = 0; i < wl_nm.size(); ++i)
        for (size_t j = 0; j < t.nodes; ++j) {
            size_t k = std::min(j + 1, t.nodes - 1);
            for (size_t v = 0; v < 4; ++v) {
                t.records[(i * t.nodes + j) * 8 + v] = q[(i * t.nodes + j) * 4 + v];
                t.records[(i * t.nodes + j) * 8 + 4 + v] = q[(i * t.nodes + k) * 4 + v];
            }
        }
}

inline std::pair<double, double> efficiency_at(const EfficiencyTable &t, size_t i, double v);

/**
 * The efficiency table for values in [lo, hi] of its variable (TableAxis: radii in
 * um, or fills of agglomerates of radius g.agglomerate_radius) at the wavelengths
 * wl_nm; `name` is the property whose texture sets the values (for errors). The
 * spacing starts at du = min(0.05, 0.25 / (x |m|)_max) (radius) or 0.05 (fill) and
 * is halved until the albedo Q_sca / Q_ext interpolated at every interval's midpoint
 * agrees with theory there to `tolerance` (relative), or until the table would
 * exceed `max_records` (wavelengths x nodes); `error` receives the largest midpoint
 * error reached.
 */
template <typename ParallelFor = SerialFor>
EfficiencyTable efficiency_table(const Grains &g, double lo, double hi,
                                 const std::vector<double> &wl_nm,
                                 const std::vector<std::complex<double>> &index,
                                 const char *name, double tolerance, size_t max_records,
                                 double &error, ParallelFor &&parallel_for = ParallelFor(),
                                 TableAxis axis = TableAxis::LogRadius) {
    const double pi = 3.14159265358979323846;
    double wl_min = *std::min_element(wl_nm.begin(), wl_nm.end()), m_max = 1.0;
    for (const auto &m : index)
        m_max = std::max(m_max, std::abs(m));
    EfficiencyTable t;
    t.axis = axis;
    double du, span;
    if (axis == TableAxis::Fill) {
        t.u0 = lo;
        du = 0.05;
        span = hi - lo;
    } else {
        double x_max = 2.0 * pi * hi / (wl_min * 1e-3) * m_max;
        t.u0 = std::log(lo);
        du = std::min(0.05, 0.25 / x_max);
        span = std::log(hi) - t.u0;
    }
    while (true) {
        t.du = du;
        t.nodes = std::max((size_t) 2, (size_t) std::ceil(span / t.du - 1e-9) + 1);
        if (axis == TableAxis::Fill) // the last node exactly at hi (fills stay <= 1)
            t.du = span / (double) (t.nodes - 1);
        fill_efficiency_table(t, g, wl_nm, index, name, parallel_for);
        // the albedo at every midpoint against theory
        std::vector<double> worst(wl_nm.size(), 0.0);
        for_each_row(wl_nm.size(), parallel_for, [&](size_t i) {
            for (size_t j = 0; j + 1 < t.nodes; ++j) {
                double r = table_value(axis, t.u0 + ((double) j + 0.5) * t.du);
                auto exact = table_point(g, axis, r, wl_nm[i], index[i], name,
                                         axis != TableAxis::Fill);
                auto [qe, qs] = efficiency_at(t, i, r);
                double rho = exact[1] / exact[0];
                worst[i] = std::max(worst[i], std::abs(qs / qe - rho) / std::max(rho, 1e-12));
            }
        });
        error = *std::max_element(worst.begin(), worst.end());
        size_t next = wl_nm.size() * (2 * t.nodes - 1);
        if (error <= tolerance || next > max_records)
            return t;
        du *= 0.5;
    }
}

/// Cubic Hermite interpolation of (Q_ext, Q_sca) in an EfficiencyTable at the value
/// v of its variable (radius in um, or fill) and wavelength row i (double precision;
/// the plugin does the same per lane)
inline std::pair<double, double> efficiency_at(const EfficiencyTable &t, size_t i, double v) {
    double pos = ((t.axis == TableAxis::Fill ? v : std::log(v)) - t.u0) / t.du;
    pos = std::min(std::max(pos, 0.0), (double) (t.nodes - 1) - 1e-9);
    size_t j = std::min((size_t) pos, t.nodes - 2);
    double s = pos - (double) j, h00 = (1.0 + 2.0 * s) * (1.0 - s) * (1.0 - s),
           h10 = s * (1.0 - s) * (1.0 - s), h01 = s * s * (3.0 - 2.0 * s),
           h11 = s * s * (s - 1.0);
    const double *rec = &t.records[(i * t.nodes + j) * 8];
    return { h00 * rec[0] + h10 * t.du * rec[2] + h01 * rec[4] + h11 * t.du * rec[6],
             h00 * rec[1] + h10 * t.du * rec[3] + h01 * rec[5] + h11 * t.du * rec[7] };
}

} // namespace powder
