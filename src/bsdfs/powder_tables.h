#pragma once

/*
 * The tables eval reads, and how it reads them. A table over the 1 nm wavelength grid
 * (spectral variants) is read as records: each interval [i, i + 1] of the grid holds the
 * values of its two nodes for every quantity, so that one packet gather per channel gives
 * what linear interpolation needs (gathers dominate the cost of eval on CPUs with slow
 * vector gathers). One packer (gather_entries, interval_records) builds every record
 * table: the grain tables (albedo, tau_o), the surface Fresnel index, the volume
 * constants (powder_volume.h) and the energy normalisation (powder_energy.h); in JIT
 * variants it gathers from the tables, so the records stay differentiable.
 */

#include <mitsuba/core/spectrum.h>
#include <mitsuba/render/interaction.h>

#include <drjit/dynamic.h>
#include <nanothread/nanothread.h>

#include <complex>
#include <tuple>
#include <vector>

#include "powder_fresnel.h"
#include "powder_optics.h"
#include "powder_registry.h"

NAMESPACE_BEGIN(mitsuba)

/// Runs row(i) for i in [0, n) on Dr.Jit's thread pool (the grain tables' rows);
/// below 32 rows (RGB and mono tables) on the calling thread: too few to share
struct DrJitParallelFor {
    template <typename Row> void operator()(size_t n, Row &&row) const {
        if (n < 32) {
            for (size_t i = 0; i < n; ++i)
                row(i);
            return;
        }
        dr::parallel_for(dr::blocked_range<size_t>(0, n, 4),
                         [&](const dr::blocked_range<size_t> &range) {
                             for (size_t i = range.begin(); i != range.end(); ++i)
                                 row(i);
                         });
    }
};

template <typename Float, typename Spectrum> struct PowderTables {
    MI_IMPORT_TYPES()
    using FloatStorage = DynamicBuffer<Float>;
    using UInt32Storage = DynamicBuffer<UInt32>;
    using UInt64Storage = DynamicBuffer<UInt64>;
    /// the spectral grid (powder_registry.h)
    static constexpr int TableSize = powder_param::TableSize;
    static constexpr float TableMin = powder_param::TableMin, TableStep = powder_param::TableStep;

    /// Entry e of the result is source[which[e]][index[e]]; differentiable (JIT: gathers)
    static FloatStorage gather_entries(const std::vector<const FloatStorage *> &source,
                                       const std::vector<uint32_t> &which,
                                       const std::vector<uint32_t> &index) {
        if constexpr (dr::is_jit_v<Float>) {
            UInt32Storage idx = dr::load<UInt32Storage>(index.data(), index.size()),
                          q = dr::load<UInt32Storage>(which.data(), which.size());
            FloatStorage out = dr::gather<FloatStorage>(*source.back(), idx);
            for (uint32_t k = (uint32_t) source.size() - 1; k-- > 0;)
                out = dr::select(q == k, dr::gather<FloatStorage>(*source[k], idx), out);
            dr::make_opaque(out);
            return out;
        } else {
            std::vector<ScalarFloat> packed(index.size());
            for (size_t e = 0; e < packed.size(); ++e)
                packed[e] = (*source[which[e]])[index[e]];
            return dr::load<FloatStorage>(packed.data(), packed.size());
        }
    }

    /// Records of the intervals of n nodes: for node i, (q0[i], q0[i + 1], q1[i], q1[i + 1],
    /// ...) of the quantities q (the last interval repeats its node)
    static FloatStorage interval_records(const std::vector<const FloatStorage *> &quantities,
                                         uint32_t n) {
        const uint32_t R = 2 * (uint32_t) quantities.size(); // entries per record
        std::vector<uint32_t> node(R * n), quantity(R * n);
        for (uint32_t i = 0; i < n; ++i)
            for (uint32_t j = 0; j < R; ++j) {
                node[R * i + j] = std::min(i + (j & 1u), n - 1);
                quantity[R * i + j] = j >> 1;
            }
        return gather_entries(quantities, quantity, node);
    }

    static FloatStorage upload(const std::vector<ScalarFloat> &v) {
        return dr::load<FloatStorage>(v.data(), v.size());
    }

    /// The entries of a table on the host, detached
    static std::vector<ScalarFloat> download(const FloatStorage &t) {
        std::vector<ScalarFloat> v(dr::width(t));
        if constexpr (dr::is_jit_v<Float>)
            dr::store(v.data(), dr::detach(t));
        else
            for (size_t i = 0; i < v.size(); ++i)
                v[i] = t[i];
        return v;
    }

    /// Spectral variants: the interval of the 1 nm grid that holds the wavelength of
    /// channel c: its first node i0 and the weight w of the next, the position t clamped
    /// inside the table (other variants: the first node). t >= 0, so its conversion to a
    /// signed integer truncates to floor(t): one instruction each way, where the unsigned
    /// conversions are sequences of instructions on CPUs without AVX-512
    /// (docs/benchmarks.md)
    static std::pair<UInt32, Float> table_interval(const SurfaceInteraction3f &si, size_t c) {
        Float t(0.f);
        if constexpr (is_spectral_v<Spectrum>)
            t = dr::clip((si.wavelengths[c] - TableMin) * (1.f / TableStep), 0.f,
                         (float) (TableSize - 1) - 1e-3f);
        Int32 i0 = Int32(t);
        return { UInt32(i0), t - Float(i0) };
    }

    /// Spectral variants: the quantities of interval records of P entries (P / 2
    /// quantities) at the channel wavelengths; assign(c, value) receives value(q),
    /// quantity q interpolated at channel c
    template <size_t P, typename Assign>
    static void read_records(const FloatStorage &records, const SurfaceInteraction3f &si,
                             Mask active, Assign &&assign) {
        for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
            UInt32 i0;
            Float w;
            std::tie(i0, w) = table_interval(si, c);
            auto v = dr::gather<dr::Array<Float, P>>(records, i0, active);
            assign(c, [&](size_t q) { return dr::lerp(v[2 * q], v[2 * q + 1], w); });
        }
    }

    /// JIT variants: interval records of one quantity (2 entries each) packed into one
    /// 64-bit word per record (the first entry in the low half), detached, for read_pairs;
    /// other variants: empty
    static UInt64Storage packed_pairs(const FloatStorage &records) {
        UInt64Storage out;
        if constexpr (dr::is_jit_v<Float>) {
            UInt32Storage i = dr::arange<UInt32Storage>((uint32_t) dr::width(records) / 2u);
            FloatStorage r = dr::detach(records);
            auto half = [&](const UInt32Storage &k) {
                return UInt64Storage(
                    dr::reinterpret_array<UInt32Storage>(dr::gather<FloatStorage>(r, k)));
            };
            out = half(2u * i) | dr::sl<32>(half(2u * i + 1u));
            dr::make_opaque(out);
        }
        return out;
    }

    /// JIT variants: read_records<2> from the packed_pairs of the records: the quantity
    /// at each channel wavelength, the same values, from one 64-bit gather per channel.
    /// On the AMD EPYC (AVX2) of docs/benchmarks.md a 64-bit gather costs less than the
    /// packet gather of 2 floats (per lane a load of 8 bytes and a transposition);
    /// detached, so that eval reads the float records where gradients flow through them
    template <typename Assign>
    static void read_pairs(const UInt64Storage &pairs, const SurfaceInteraction3f &si,
                           Mask active, Assign &&assign) {
        for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
            UInt32 i0;
            Float w;
            std::tie(i0, w) = table_interval(si, c);
            UInt64 v = dr::gather<UInt64>(pairs, i0, active);
            assign(c, dr::lerp(dr::reinterpret_array<Float>(UInt32(v)),
                               dr::reinterpret_array<Float>(UInt32(dr::sr<32>(v))), w));
        }
    }

    /// A table at the channel wavelengths: linear interpolation on the 1 nm grid
    /// (spectral), or one entry per channel (RGB, mono)
    static UnpolarizedSpectrum lookup(const FloatStorage &table, const SurfaceInteraction3f &si,
                                      Mask active) {
        UnpolarizedSpectrum out(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                UInt32 i0;
                Float w;
                std::tie(i0, w) = table_interval(si, c);
                out[c] = dr::lerp(dr::gather<Float>(table, i0, active),
                                  dr::gather<Float>(table, i0 + 1u, active), w);
            }
        } else {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                out[c] = dr::gather<Float>(table, UInt32((uint32_t) c), active);
        }
        return out;
    }

    // ------------------------------------------------------------- Fresnel index

    /// surface_fresnel: the grain index n + i k at the table wavelengths, as per-channel
    /// constants (RGB, mono; and spectral when the index is the same at every wavelength)
    /// or interval records (eta, k) of the 1 nm grid
    struct FresnelIndex {
        bool constant = false; ///< one index at every wavelength
        UnpolarizedSpectrum eta = 0.f, k = 0.f, inv_f1 = 0.f;
        FloatStorage records;
    };

    /// The FresnelIndex of m at the wavelengths (nm); the factor F(c) / F(1) is undefined
    /// where the interface reflects nothing at normal incidence (m = 1)
    static FresnelIndex fresnel_index(const std::vector<std::complex<double>> &index,
                                      const std::vector<double> &wavelengths) {
        std::vector<ScalarFloat> eta, k;
        for (size_t i = 0; i < index.size(); ++i) {
            const std::complex<double> &m = index[i];
            // below 1e-5 (|m - 1| < 0.0063) F(1) is ill-conditioned in single precision
            if (double f1 = powder::fresnel_normal(m.real(), m.imag()); !(f1 >= 1e-5))
                Throw("powder: property \"surface_fresnel\" = \"fresnel\": the grain index "
                      "%g + %gi at %g nm is too close to 1: the smooth interface reflects "
                      "almost nothing (F(1) = %g < 1e-5), and the factor F(c) / F(1) is not "
                      "defined to single precision", m.real(), m.imag(), wavelengths[i], f1);
            eta.push_back((ScalarFloat) m.real());
            k.push_back((ScalarFloat) m.imag());
        }
        FresnelIndex out;
        out.constant =
            std::all_of(eta.begin(), eta.end(), [&](ScalarFloat v) { return v == eta[0]; }) &&
            std::all_of(k.begin(), k.end(), [&](ScalarFloat v) { return v == k[0]; });
        if (is_spectral_v<Spectrum> && !out.constant) {
            FloatStorage e = upload(eta), kk = upload(k);
            out.records = interval_records({ &e, &kk }, (uint32_t) eta.size());
            return out;
        }
        for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
            size_t j = is_spectral_v<Spectrum> ? 0 : c;
            out.eta[c] = eta[j];
            out.k[c] = k[j];
            out.inv_f1[c] =
                (ScalarFloat) (1.0 / powder::fresnel_normal((double) eta[j], (double) k[j]));
        }
        return out;
    }

    /// surface_fresnel: F(c) / F(1) per channel at the cosine c of the half vector
    static UnpolarizedSpectrum fresnel_factor(const FresnelIndex &f, const SurfaceInteraction3f &si,
                                              const Float &c, Mask active) {
        if (is_spectral_v<Spectrum> && !f.constant) {
            UnpolarizedSpectrum out(0.f);
            read_records<4>(f.records, si, active, [&](size_t ch, auto value) {
                Float eta = value(0), k = value(1);
                out[ch] = powder::fresnel_unpolarized(c, eta, k) / powder::fresnel_normal(eta, k);
            });
            return out;
        }
        return powder::fresnel_unpolarized(UnpolarizedSpectrum(c), f.eta, f.k) * f.inv_f1;
    }

    // ------------------------------------------------------------- Mie tables

    /// The albedo table of constant grains: rho, and the efficiencies of each population
    /// (attributes), per table wavelength
    struct MieTables {
        FloatStorage rho, qext, qsca, qext2, qsca2;
        DRJIT_STRUCT(MieTables, rho, qext, qsca, qext2, qsca2)
    };

    /// Mie efficiencies and rho = Q_sca / Q_ext (two populations: docs/model.md); with
    /// `params` (the grain parameters whose gradients are tracked, each with its column of
    /// derivatives), rho's first derivatives with respect to them are attached to the AD
    /// graph as tangents. The rows are spread over Dr.Jit's threads.
    static MieTables
    mie_tables(const powder::Grains &grains, const std::vector<double> &wavelengths,
               const std::vector<powder::PopulationIndex> &index,
               const std::vector<std::pair<const Float *, powder_param::Id>> &params) {
        std::vector<powder::AlbedoRow> rows = powder::albedo_table(
            grains, wavelengths, index, !params.empty(), DrJitParallelFor());
        size_t n = rows.size();
        auto column = [&](auto get) {
            std::vector<ScalarFloat> v(n);
            for (size_t i = 0; i < n; ++i)
                v[i] = (ScalarFloat) get(rows[i]);
            return upload(v);
        };
        MieTables t{ column([](const powder::AlbedoRow &r) { return r.rho; }),
                     column([](const powder::AlbedoRow &r) { return r.q_ext[0]; }),
                     column([](const powder::AlbedoRow &r) { return r.q_sca[0]; }),
                     column([](const powder::AlbedoRow &r) { return r.q_ext[1]; }),
                     column([](const powder::AlbedoRow &r) { return r.q_sca[1]; }) };
        // value unchanged (the differences are zero), first derivatives exact
        if constexpr (dr::is_diff_v<Float>)
            for (auto &[param, id] : params)
                t.rho = t.rho + column([id = id](const powder::AlbedoRow &r) {
                    return r.d[id];
                }) * (*param - dr::detach(*param));
        dr::make_opaque(t.rho);
        return t;
    }

    // ------------------------------------------------ spatially varying grains

    /// The efficiency table of spatially varying grains as eval reads it
    struct GrainTexture {
        powder::EfficiencyTable table;
        FloatStorage records;
        ScalarFloat u0 = 0.f, du = 1.f;
    };

    /// Upload an efficiency table (powder::efficiency_table) for grain_efficiencies
    static GrainTexture grain_texture(powder::EfficiencyTable &&table) {
        GrainTexture g;
        std::vector<ScalarFloat> rec(table.records.begin(), table.records.end());
        g.records = upload(rec);
        dr::make_opaque(g.records);
        g.u0 = (ScalarFloat) table.u0;
        g.du = (ScalarFloat) table.du;
        g.table = std::move(table);
        return g;
    }

    /// (Q_ext, Q_sca) per channel of grains of radius r (um, per lane; or of the fill of
    /// agglomerates) from the efficiency table: cubic Hermite in ln r (in the fill), and in
    /// spectral variants linear in wavelength on the 1 nm grid, as the constant tables
    static std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    grain_efficiencies(const GrainTexture &g, const Float &r, const SurfaceInteraction3f &si,
                       Mask active) {
        uint32_t nodes = (uint32_t) g.table.nodes;
        Float u = g.table.axis == powder::TableAxis::Fill ? r : dr::log(r);
        Float t = dr::clip((u - g.u0) * (1.f / g.du), 0.f, (float) (nodes - 1) - 1e-3f);
        UInt32 j = UInt32(dr::floor(dr::detach(t)));
        Float s = t - Float(j), one_s = 1.f - s,
              h00 = (1.f + 2.f * s) * dr::square(one_s), h10 = s * dr::square(one_s) * g.du,
              h01 = dr::square(s) * (3.f - 2.f * s), h11 = dr::square(s) * (s - 1.f) * g.du;
        auto hermite = [&](const UInt32 &row) {
            auto v = dr::gather<dr::Array<Float, 8>>(g.records, row * nodes + j, active);
            return std::pair<Float, Float>(h00 * v[0] + h10 * v[2] + h01 * v[4] + h11 * v[6],
                                           h00 * v[1] + h10 * v[3] + h01 * v[5] + h11 * v[7]);
        };
        UnpolarizedSpectrum qe, qs;
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                UInt32 i0;
                Float w;
                std::tie(i0, w) = table_interval(si, c);
                auto [e0, s0] = hermite(i0);
                auto [e1, s1] = hermite(i0 + 1u);
                qe[c] = dr::lerp(e0, e1, w);
                qs[c] = dr::lerp(s0, s1, w);
            }
        } else {
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c)
                std::tie(qe[c], qs[c]) = hermite(UInt32((uint32_t) c));
        }
        return { qe, qs };
    }

    /// The albedo of spatially varying grains per lane: `n` populations, population j of
    /// radius r[j] (per lane) with the efficiencies of the table tables[j] (of its material)
    /// and, for j >= 1, fraction f[j] (per lane; population 1 has 1 - the others)
    static UnpolarizedSpectrum grain_albedo(const GrainTexture *const *tables, const Float *r,
                                            const Float *f, size_t n,
                                            const SurfaceInteraction3f &si, Mask active) {
        auto [qe1, qs1] = grain_efficiencies(*tables[0], r[0], si, active);
        if (n == 1)
            return qs1 / qe1;
        if (n == 2) { // (as before several materials: the same arithmetic)
            auto [qe2, qs2] = grain_efficiencies(*tables[1], r[1], si, active);
            return powder::population_mix(qe1, qs1, r[0], qe2, qs2, r[1], f[1]);
        }
        Float f1 = 1.f;
        for (size_t j = 1; j < n; ++j)
            f1 -= f[j];
        Float w1 = dr::maximum(f1, 0.f) / r[0];
        UnpolarizedSpectrum num = w1 * qs1, den = w1 * qe1;
        for (size_t j = 1; j < n; ++j) {
            auto [qe, qs] = grain_efficiencies(*tables[j], r[j], si, active);
            Float w = f[j] / r[j];
            num += w * qs;
            den += w * qe;
        }
        return num / den;
    }
};

NAMESPACE_END(mitsuba)
