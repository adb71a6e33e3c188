#pragma once

/*
 * The grains of a powder: the tables of their albedo (Mie theory, or the efficiency table
 * of spatially varying grains), of tau_o (Fresnel) and of the surface Fresnel index at the
 * table wavelengths, rebuilt when a grain parameter changes, and what eval reads of them
 * per interaction. A member of the BSDF (powder.cpp), beside the properties
 * (PowderParams) it is built from.
 */

#include "powder_params.h"
#include "powder_tables.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> struct PowderGrains {
    MI_IMPORT_TYPES(Texture)
    using Params = PowderParams<Float, Spectrum>;
    using Tables = PowderTables<Float, Spectrum>;
    using Textures = PowderTextures<Float, Spectrum>;
    using FloatStorage = typename Tables::FloatStorage;
    static constexpr int TableSize = Tables::TableSize;
    static constexpr float TableMin = Tables::TableMin, TableStep = Tables::TableStep;

    /// The grain index at the wavelengths (nm) of the grain tables: a 1 nm grid for
    /// spectral variants, the evaluation wavelengths otherwise; with it tau_o (Fresnel)
    /// and the surface_fresnel index
    explicit PowderGrains(const Params &p) {
        if constexpr (is_spectral_v<Spectrum>) {
            for (int i = 0; i < TableSize; ++i)
                table_wavelengths.push_back(TableMin + i * TableStep);
        } else if constexpr (is_rgb_v<Spectrum>) {
            table_wavelengths.assign(p.rgb_wavelengths, p.rgb_wavelengths + 3);
        } else {
            table_wavelengths.push_back(p.wavelength);
        }
        for (double wl : table_wavelengths)
            grain_index.push_back(p.optics.eval(wl * 1e-3)); // throws if outside the table
        if (!p.albedo)
            warn_crystallite_size(p);
        if (!p.tau_given) {
            std::vector<ScalarFloat> tau;
            for (const auto &m : grain_index)
                tau.push_back((ScalarFloat) powder::tau_o_fresnel(m.real()));
            tau_table = Tables::upload(tau);
            tau_table_constant =
                std::all_of(tau.begin(), tau.end(), [&](ScalarFloat t) { return t == tau[0]; });
        }
        if (p.surface_fresnel)
            fresnel = Tables::fresnel_index(grain_index, table_wavelengths);
    }

    /// Largest crystallite size parameter for which a mixing rule holds (docs/model.md)
    static constexpr double CrystalliteLimit = 0.5;

    /// Agglomerates: warn when the crystallites are too large for a mixing rule
    /// (size parameter 2 pi r |n + ik| / lambda above CrystalliteLimit at some wavelength)
    void warn_crystallite_size(const Params &p) const {
        if (p.grain_model != powder::GrainModel::Agglomerate)
            return;
        std::vector<double> x = powder::crystallite_size_parameters(
            Params::value_of(p.radius), table_wavelengths, grain_index);
        size_t worst = 0, over = 0;
        double longest = 0.0; // longest wavelength (nm) above the limit
        for (size_t i = 0; i < x.size(); ++i) {
            if (x[i] > x[worst])
                worst = i;
            if (x[i] > CrystalliteLimit) {
                ++over;
                longest = std::max(longest, table_wavelengths[i]);
            }
        }
        if (over > 0)
            Log(Warn,
                "powder: crystallites of radius %g um have the size parameter 2 pi r |n + ik| "
                "/ lambda = %.3g at %g nm, above %g (the limit of an effective-medium mixing "
                "rule) at %zu of the %zu wavelengths evaluated, the longest %g nm; the "
                "agglomerate albedo is outside the model's validity there (docs/model.md, \"Grain "
                "models\")", Params::value_of(p.radius), x[worst], table_wavelengths[worst],
                CrystalliteLimit, over, x.size(), longest);
    }

    // ------------------------------------------------------------- grains

    /// Single-scattering albedo per channel: the `albedo` texture or the grain tables
    UnpolarizedSpectrum albedo(const Params &p, const SurfaceInteraction3f &si,
                               Mask active) const {
        if (p.albedo)
            return p.albedo->eval(si, active);
        if (p.grain_textured())
            return grain_texture_albedo(p, si, active);
        if constexpr (is_spectral_v<Spectrum>)
            return lookup(si, active).first;
        else
            return rho_channels;
    }

    /// Extrapolation ratio per channel: the `tau_o` property or the Fresnel table
    UnpolarizedSpectrum tau_o(const Params &p, const SurfaceInteraction3f &si,
                              Mask active) const {
        if (p.tau_given)
            return UnpolarizedSpectrum(p.at(powder_param::TauO, si, active));
        if constexpr (is_spectral_v<Spectrum>)
            return lookup(si, active).second;
        else
            return tau_channels;
    }

    /// Spectral variants: (rho, tau_o) per channel from the records of `packed`, with the
    /// same linear interpolation as Tables::lookup in one packet gather per channel
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    lookup(const SurfaceInteraction3f &si, Mask active) const {
        UnpolarizedSpectrum rho(0.f), tau(0.f);
        Tables::template read_records<4>(packed, si, active, [&](size_t c, auto value) {
            rho[c] = value(0);
            tau[c] = value(1);
        });
        return { rho, tau };
    }

    /// The grain tables after a change of the grain parameters (`keys`: those edited;
    /// none: all), and what eval reads of them
    void update(const Params &p, const std::vector<std::string> &keys) {
        bool grains_changed = keys.empty();
        for (size_t i = 0; i < powder_param::Count; ++i)
            if (powder_param::is_grain_param((powder_param::Id) i))
                grains_changed |= string::contains(keys, powder_param::Table[i].name);
        if (!p.albedo && p.grain_textured())
            update_grain_texture_table(p);
        else if (!p.albedo && grains_changed)
            update_mie_tables(p);
        if (p.albedo && (keys.empty() || string::contains(keys, "albedo")))
            Textures::check_albedo(p.albedo.get());

        if constexpr (is_spectral_v<Spectrum>) {
            // records (rho[i], rho[i + 1], tau[i], tau[i + 1]) for lookup (zeros for a
            // table not in use); differentiable through the gathers from the tables
            FloatStorage zero = dr::zeros<FloatStorage>(TableSize);
            packed = Tables::interval_records(
                { p.albedo ? &zero : &mie.rho, p.tau_given ? &zero : &tau_table },
                (uint32_t) TableSize);
        } else {
            // RGB and mono: one value per channel, as opaque scalars, so that eval reads a
            // broadcast value instead of gathering
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                if (!p.albedo)
                    rho_channels[c] = dr::gather<Float>(mie.rho, UInt32((uint32_t) c));
                if (!p.tau_given)
                    tau_channels[c] = dr::gather<Float>(tau_table, UInt32((uint32_t) c));
            }
            dr::make_opaque(rho_channels, tau_channels);
        }
    }

    /// The grains of the constant grain parameters
    static powder::Grains constant_grains(const Params &p) {
        return { Params::value_of(p.radius), Params::value_of(p.radius2),
                 Params::value_of(p.fraction2), p.two_populations, p.grain_model,
                 Params::value_of(p.agglomerate_radius), Params::value_of(p.agglomerate_fill),
                 p.mixing };
    }

    /// The Mie tables; rho's derivatives are attached as tangents when gradients are
    /// tracked on a grain parameter
    void update_mie_tables(const Params &p) {
        std::vector<std::pair<const Float *, double powder::AlbedoRow::*>> params;
        for (auto [id, d] : { std::pair{ powder_param::Radius, &powder::AlbedoRow::d_r1 },
                              std::pair{ powder_param::Radius2, &powder::AlbedoRow::d_r2 },
                              std::pair{ powder_param::Fraction2, &powder::AlbedoRow::d_f2 },
                              std::pair{ powder_param::AgglomerateRadius,
                                         &powder::AlbedoRow::d_ra },
                              std::pair{ powder_param::AgglomerateFill,
                                         &powder::AlbedoRow::d_fill } })
            if (p.in_use(id))
                params.emplace_back(&p[id], d);
        bool tangents = false;
        if constexpr (dr::is_diff_v<Float>)
            for (auto &gp : params)
                tangents |= dr::grad_enabled(*gp.first);
        if (!tangents)
            params.clear();
        mie = Tables::mie_tables(constant_grains(p), table_wavelengths, grain_index, params);
    }

    /// Spatially varying grains: relative accuracy of the tabulated albedo (checked at
    /// every interval's midpoint) and the largest table (wavelengths x nodes)
    static constexpr double GrainTableTolerance = 2e-4;
    static constexpr size_t GrainTableRecords = 200000;

    /**
     * Spatially varying grains (a radius, radius2, fraction2 or agglomerate_radius
     * texture): tabulate Q_ext and Q_sca over ln r (powder::efficiency_table) for the
     * radii the textures hold, widened by a factor 1.25 each way so that edits of the
     * texture usually stay inside (outside, the table is rebuilt); with an
     * agglomerate_fill texture, over the fill (widened by 0.05 each way inside (0, 1])
     * at the float agglomerate_radius. The table is rebuilt when the agglomerate
     * property it holds at one value changes. eval interpolates per lane and mixes the
     * populations (grain_texture_albedo). Differentiable through the interpolation.
     */
    void update_grain_texture_table(const Params &p) {
        bool fill = p.table_param() == powder_param::AgglomerateFill;
        if (fill && p.textured(powder_param::AgglomerateRadius))
            Throw("powder: properties \"agglomerate_fill\" and \"agglomerate_radius\" "
                  "are both textures; the albedo table of spatially varying agglomerates "
                  "runs over one of them: give the other as a float");
        // the table holds the other agglomerate property at one value: its gradient
        // would be lost
        powder_param::Id held = fill ? powder_param::AgglomerateRadius
                                     : powder_param::AgglomerateFill;
        if constexpr (dr::is_diff_v<Float>)
            if (p.agglomerate() && dr::grad_enabled(p[held]))
                Throw("powder: property \"%s\" is not differentiable while \"%s\" is a "
                      "texture (the albedo table runs over the texture's values at one "
                      "%s)", powder_param::Table[held].name,
                      powder_param::Table[p.table_param()].name, powder_param::Table[held].name);
        double held_value = p.agglomerate() ? Params::value_of(p[held]) : 0.0;
        auto [lo, hi] = p.value_range(p.table_param());
        if (p.two_populations && !p.agglomerate()) {
            auto [lo2, hi2] = p.value_range(powder_param::Radius2);
            lo = std::min(lo, lo2);
            hi = std::max(hi, hi2);
        }
        if (grain.table.nodes > 0 && lo >= grain_table_lo && hi <= grain_table_hi &&
            held_value == grain_table_held)
            return; // the current table covers the values
        powder::Grains g{ 1.0, 1.0, 0.0, false, p.grain_model, 1.0, 0.5, p.mixing };
        double lo_t, hi_t;
        if (fill) {
            // fills in (0, 1]: widened by 0.05 each way where they can be (a single
            // fill of 1 gets the interval [0.95, 1])
            lo_t = std::max(lo - 0.05, 0.5 * lo);
            hi_t = std::min(hi + 0.05, 1.0);
            g.agglomerate_radius = Params::value_of(p.agglomerate_radius);
        } else {
            lo_t = lo / 1.25;
            hi_t = hi * 1.25;
            if (p.grain_model != powder::GrainModel::Slab) {
                // keep the widened range inside the size parameters Mie accepts
                auto [wl_lo, wl_hi] = std::minmax_element(table_wavelengths.begin(),
                                                          table_wavelengths.end());
                lo_t = std::max(lo_t, std::min(lo, 1e-3 * *wl_hi * 1e-3 / (2.0 * M_PI)));
                hi_t = std::min(hi_t, std::max(hi, 200.0 * *wl_lo * 1e-3 / (2.0 * M_PI)));
            }
            hi_t = std::max(hi_t, lo_t * 1.001);
            g.agglomerate_fill = Params::value_of(p.agglomerate_fill);
        }
        build_grain_texture_table(p, g, lo, hi, lo_t, hi_t,
                                  fill ? powder::TableAxis::Fill : powder::TableAxis::LogRadius);
        grain_table_held = held_value;
    }

    /// Build the grain texture table over [lo_t, hi_t] of its variable (covering the
    /// texture values [lo, hi]) and upload its records
    void build_grain_texture_table(const Params &p, const powder::Grains &grains, double lo,
                                   double hi, double lo_t, double hi_t,
                                   powder::TableAxis axis) {
        bool fill = axis == powder::TableAxis::Fill;
        double error = 0.0;
        grain = Tables::grain_texture(powder::efficiency_table(
            grains, lo_t, hi_t, table_wavelengths, grain_index,
            powder_param::Table[p.table_param()].name, GrainTableTolerance, GrainTableRecords,
            error, DrJitParallelFor(), axis));
        if (error > GrainTableTolerance)
            Log(Warn, "powder: the albedo table of %s %g-%g%s is accurate to %.2g "
                      "(relative, at the midpoints of its %zu nodes), not %g: the values "
                      "span too many Mie resonances for %zu records; narrow the texture's "
                      "range", fill ? "fills" : "radii", lo_t, hi_t, fill ? "" : " um",
                error, grain.table.nodes, GrainTableTolerance, GrainTableRecords);
        grain_table_lo = lo_t;
        grain_table_hi = hi_t;
        // a mean albedo for the sampling weights only: at the middle of the range
        double r_mid = fill ? 0.5 * (lo + hi) : std::sqrt(lo * hi), rho = 0.0;
        for (size_t i = 0; i < table_wavelengths.size(); ++i) {
            auto [qe, qs] = powder::efficiency_at(grain.table, i, r_mid);
            rho += qs / qe;
        }
        grain_rho_mean = rho / (double) table_wavelengths.size();
        // the constant-radius tables are not used; keep them valid for packing
        FloatStorage zero = dr::zeros<FloatStorage>(table_wavelengths.size());
        mie = { zero, zero, zero, zero, zero };
    }

    /// The albedo of spatially varying grains per lane (docs/model.md; slab: Q_ext = 1,
    /// Q_sca = rho)
    UnpolarizedSpectrum grain_texture_albedo(const Params &p, const SurfaceInteraction3f &si,
                                             Mask active) const {
        Float r1 = p.at(p.table_param(), si, active);
        if (!p.two_populations)
            return Tables::grain_albedo(grain, r1, nullptr, nullptr, si, active);
        Float r2 = p.at(powder_param::Radius2, si, active),
              f2 = p.at(powder_param::Fraction2, si, active);
        return Tables::grain_albedo(grain, r1, &r2, &f2, si, active);
    }

    // grain tables (powder_tables.h), at the table wavelengths
    std::vector<double> table_wavelengths;         ///< nm
    std::vector<std::complex<double>> grain_index; ///< n + i k at those wavelengths
    typename Tables::MieTables mie;
    FloatStorage tau_table;
    bool tau_table_constant = false;     ///< every entry of tau_table is the same
    FloatStorage packed;                 ///< spectral: records for lookup
    /// RGB and mono: the entries of the albedo and tau_o tables, one per channel
    UnpolarizedSpectrum rho_channels = 0.f, tau_channels = 0.f;
    typename Tables::FresnelIndex fresnel; ///< surface_fresnel
    /// spatially varying grains: the efficiency table (grain_texture_albedo), the
    /// values it covers and the agglomerate property it holds
    typename Tables::GrainTexture grain;
    double grain_table_lo = 0.0, grain_table_hi = 0.0, grain_table_held = 0.0;
    double grain_rho_mean = 0.5;

    POWDER_TRAVERSE_MEMBERS(rho_channels, tau_channels, packed, mie, tau_table,
                            fresnel.records, grain.records)
};

NAMESPACE_END(mitsuba)
