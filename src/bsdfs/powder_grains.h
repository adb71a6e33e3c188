#pragma once

/*
 * The grains of a powder: the tables of their albedo (Mie theory, or the efficiency table
 * of spatially varying grains), of tau_o (Fresnel) and of the surface Fresnel index at the
 * table wavelengths, rebuilt when a grain parameter changes, and what eval reads of them
 * per interaction. The base of the BSDF (powder.cpp).
 */

#include "powder_params.h"
#include "powder_tables.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class PowderGrains : public PowderParams<Float, Spectrum> {
public:
    MI_IMPORT_TYPES(Texture)
    using Params = PowderParams<Float, Spectrum>;
    using typename Params::Tables;
    using typename Params::Textures;
    using typename Params::FloatStorage;
    using Params::TableSize, Params::TableMin, Params::TableStep;
    using Params::at, Params::textured, Params::in_use, Params::member, Params::value_of,
        Params::agglomerate, Params::grain_textured, Params::table_param, Params::value_range,
        Params::texture_values;
    // the properties (powder_params.h)
    using Params::m_agglomerate_fill, Params::m_agglomerate_radius, Params::m_albedo,
        Params::m_fraction2, Params::m_grain_model, Params::m_mixing, Params::m_optics,
        Params::m_radius, Params::m_radius2, Params::m_rgb_wavelengths,
        Params::m_surface_fresnel, Params::m_tau_given, Params::m_two_populations,
        Params::m_wavelength, Params::m_g, Params::m_tau_o, Params::m_textures;

protected:
    /// The grain index at the wavelengths (nm) of the grain tables: a 1 nm grid for
    /// spectral variants, the evaluation wavelengths otherwise; with it tau_o (Fresnel)
    /// and the surface_fresnel index
    void read_grain_index() {
        if constexpr (is_spectral_v<Spectrum>) {
            for (int i = 0; i < TableSize; ++i)
                m_table_wavelengths.push_back(TableMin + i * TableStep);
        } else if constexpr (is_rgb_v<Spectrum>) {
            m_table_wavelengths.assign(m_rgb_wavelengths, m_rgb_wavelengths + 3);
        } else {
            m_table_wavelengths.push_back(m_wavelength);
        }
        for (double wl : m_table_wavelengths)
            m_index.push_back(m_optics.eval(wl * 1e-3)); // throws if outside the table
        if (!m_albedo)
            warn_crystallite_size();
        if (!m_tau_given) {
            std::vector<ScalarFloat> tau;
            for (const auto &m : m_index)
                tau.push_back((ScalarFloat) powder::tau_o_fresnel(m.real()));
            m_tau_table = Tables::load(tau);
            m_tau_table_constant =
                std::all_of(tau.begin(), tau.end(), [&](ScalarFloat t) { return t == tau[0]; });
        }
        if (m_surface_fresnel)
            m_fresnel = Tables::fresnel_index(m_index, m_table_wavelengths);
    }

    /// Largest crystallite size parameter for which a mixing rule holds (docs/model.md)
    static constexpr double CrystalliteLimit = 0.5;

    /// Agglomerates: warn when the crystallites are too large for a mixing rule
    /// (size parameter 2 pi r |n + ik| / lambda above CrystalliteLimit at some wavelength)
    void warn_crystallite_size() const {
        if (m_grain_model != powder::GrainModel::Agglomerate)
            return;
        std::vector<double> x = powder::crystallite_size_parameters(
            value_of(m_radius), m_table_wavelengths, m_index);
        size_t worst = 0, over = 0;
        double longest = 0.0; // longest wavelength (nm) above the limit
        for (size_t i = 0; i < x.size(); ++i) {
            if (x[i] > x[worst])
                worst = i;
            if (x[i] > CrystalliteLimit) {
                ++over;
                longest = std::max(longest, m_table_wavelengths[i]);
            }
        }
        if (over > 0)
            Log(Warn,
                "powder: crystallites of radius %g um have the size parameter 2 pi r |n + ik| "
                "/ lambda = %.3g at %g nm, above %g (the limit of an effective-medium mixing "
                "rule) at %zu of the %zu wavelengths evaluated, the longest %g nm; the "
                "agglomerate albedo is outside the model's validity there (docs/model.md, \"Grain "
                "models\")", value_of(m_radius), x[worst], m_table_wavelengths[worst],
                CrystalliteLimit, over, x.size(), longest);
    }

    // ------------------------------------------------------------- grains

    /// Single-scattering albedo per channel: the `albedo` texture or the grain tables
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if (m_albedo)
            return m_albedo->eval(si, active);
        if (grain_textured())
            return grain_texture_albedo(si, active);
        if constexpr (is_spectral_v<Spectrum>)
            return lookup_grains(si, active).first;
        else
            return m_rho_channels;
    }

    /// Extrapolation ratio per channel: the `tau_o` property or the Fresnel table
    UnpolarizedSpectrum tau_o(const SurfaceInteraction3f &si, Mask active) const {
        if (m_tau_given)
            return UnpolarizedSpectrum(at(powder_param::TauO, si, active));
        if constexpr (is_spectral_v<Spectrum>)
            return lookup_grains(si, active).second;
        else
            return m_tau_channels;
    }

    /// Spectral variants: (rho, tau_o) per channel from the records of m_packed, with the
    /// same linear interpolation as Tables::lookup in one packet gather per channel
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    lookup_grains(const SurfaceInteraction3f &si, Mask active) const {
        UnpolarizedSpectrum rho(0.f), tau(0.f);
        Tables::template read_records<4>(m_packed, si, active, [&](size_t c, auto value) {
            rho[c] = value(0);
            tau[c] = value(1);
        });
        return { rho, tau };
    }

    /// The grain tables after a change of the grain parameters (`keys`: those edited;
    /// none: all), and what eval reads of them
    void update_grains(const std::vector<std::string> &keys) {
        bool grains_changed = keys.empty();
        for (size_t i = 0; i < powder_param::Count; ++i)
            if (powder_param::is_grain_param((powder_param::Id) i))
                grains_changed |= string::contains(keys, powder_param::Table[i].name);
        if (!m_albedo && grain_textured())
            update_grain_texture_table();
        else if (!m_albedo && grains_changed)
            update_mie_tables();
        if (m_albedo && (keys.empty() || string::contains(keys, "albedo")))
            Textures::check_albedo(m_albedo.get(), TableSize, TableMin);

        if constexpr (is_spectral_v<Spectrum>) {
            // records (rho[i], rho[i + 1], tau[i], tau[i + 1]) for lookup_grains (zeros for
            // a table not in use); differentiable through the gathers from the tables
            FloatStorage zeros = dr::zeros<FloatStorage>(TableSize);
            m_packed = Tables::interval_records(
                { m_albedo ? &zeros : &m_mie.rho, m_tau_given ? &zeros : &m_tau_table },
                (uint32_t) TableSize);
        } else {
            // RGB and mono: one value per channel, as opaque scalars, so that eval reads a
            // broadcast value instead of gathering
            for (size_t c = 0; c < dr::size_v<UnpolarizedSpectrum>; ++c) {
                if (!m_albedo)
                    m_rho_channels[c] = dr::gather<Float>(m_mie.rho, UInt32((uint32_t) c));
                if (!m_tau_given)
                    m_tau_channels[c] = dr::gather<Float>(m_tau_table, UInt32((uint32_t) c));
            }
            dr::make_opaque(m_rho_channels, m_tau_channels);
        }
    }

    /// The grains of the constant grain parameters
    powder::Grains grains() const {
        return { value_of(m_radius), value_of(m_radius2), value_of(m_fraction2),
                 m_two_populations, m_grain_model, value_of(m_agglomerate_radius),
                 value_of(m_agglomerate_fill), m_mixing };
    }

    /// The Mie tables; rho's derivatives are attached as tangents when gradients are
    /// tracked on a grain parameter
    void update_mie_tables() {
        std::vector<std::pair<const Float *, double powder::AlbedoRow::*>> params;
        for (auto [p, d] : { std::pair{ powder_param::Radius, &powder::AlbedoRow::d_r1 },
                             std::pair{ powder_param::Radius2, &powder::AlbedoRow::d_r2 },
                             std::pair{ powder_param::Fraction2, &powder::AlbedoRow::d_f2 },
                             std::pair{ powder_param::AgglomerateRadius,
                                        &powder::AlbedoRow::d_ra },
                             std::pair{ powder_param::AgglomerateFill,
                                        &powder::AlbedoRow::d_fill } })
            if (in_use(p))
                params.emplace_back(&(this->*member(p)), d);
        bool tangents = false;
        if constexpr (dr::is_diff_v<Float>)
            for (auto &gp : params)
                tangents |= dr::grad_enabled(*gp.first);
        if (!tangents)
            params.clear();
        m_mie = Tables::mie_tables(grains(), m_table_wavelengths, m_index, params);
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
    void update_grain_texture_table() {
        bool fill = table_param() == powder_param::AgglomerateFill;
        if (fill && textured(powder_param::AgglomerateRadius))
            Throw("powder: properties \"agglomerate_fill\" and \"agglomerate_radius\" "
                  "are both textures; the albedo table of spatially varying agglomerates "
                  "runs over one of them: give the other as a float");
        // the table holds the other agglomerate property at one value: its gradient
        // would be lost
        powder_param::Id held = fill ? powder_param::AgglomerateRadius
                                     : powder_param::AgglomerateFill;
        if constexpr (dr::is_diff_v<Float>)
            if (agglomerate() && dr::grad_enabled(this->*member(held)))
                Throw("powder: property \"%s\" is not differentiable while \"%s\" is a "
                      "texture (the albedo table runs over the texture's values at one "
                      "%s)", powder_param::Table[held].name,
                      powder_param::Table[table_param()].name, powder_param::Table[held].name);
        double held_value = agglomerate() ? value_of(this->*member(held)) : 0.0;
        auto [lo, hi] = value_range(table_param());
        if (m_two_populations && !agglomerate()) {
            auto [lo2, hi2] = value_range(powder_param::Radius2);
            lo = std::min(lo, lo2);
            hi = std::max(hi, hi2);
        }
        if (m_grain.table.nodes > 0 && lo >= m_grain_table_lo && hi <= m_grain_table_hi &&
            held_value == m_grain_table_held)
            return; // the current table covers the values
        powder::Grains g{ 1.0, 1.0, 0.0, false, m_grain_model, 1.0, 0.5, m_mixing };
        double lo_t, hi_t;
        if (fill) {
            // fills in (0, 1]: widened by 0.05 each way where they can be (a single
            // fill of 1 gets the interval [0.95, 1])
            lo_t = std::max(lo - 0.05, 0.5 * lo);
            hi_t = std::min(hi + 0.05, 1.0);
            g.agglomerate_radius = value_of(m_agglomerate_radius);
        } else {
            lo_t = lo / 1.25;
            hi_t = hi * 1.25;
            if (m_grain_model != powder::GrainModel::Slab) {
                // keep the widened range inside the size parameters Mie accepts
                auto [wl_lo, wl_hi] = std::minmax_element(m_table_wavelengths.begin(),
                                                          m_table_wavelengths.end());
                lo_t = std::max(lo_t, std::min(lo, 1e-3 * *wl_hi * 1e-3 / (2.0 * M_PI)));
                hi_t = std::min(hi_t, std::max(hi, 200.0 * *wl_lo * 1e-3 / (2.0 * M_PI)));
            }
            hi_t = std::max(hi_t, lo_t * 1.001);
            g.agglomerate_fill = value_of(m_agglomerate_fill);
        }
        build_grain_texture_table(g, lo, hi, lo_t, hi_t,
                                  fill ? powder::TableAxis::Fill : powder::TableAxis::LogRadius);
        m_grain_table_held = held_value;
    }

    /// Build the grain texture table over [lo_t, hi_t] of its variable (covering the
    /// texture values [lo, hi]) and upload its records
    void build_grain_texture_table(const powder::Grains &grains, double lo, double hi,
                                   double lo_t, double hi_t, powder::TableAxis axis) {
        bool fill = axis == powder::TableAxis::Fill;
        double error = 0.0;
        m_grain = Tables::grain_texture(powder::efficiency_table(
            grains, lo_t, hi_t, m_table_wavelengths, m_index,
            powder_param::Table[table_param()].name, GrainTableTolerance, GrainTableRecords,
            error, DrJitParallelFor(), axis));
        if (error > GrainTableTolerance)
            Log(Warn, "powder: the albedo table of %s %g-%g%s is accurate to %.2g "
                      "(relative, at the midpoints of its %zu nodes), not %g: the values "
                      "span too many Mie resonances for %zu records; narrow the texture's "
                      "range", fill ? "fills" : "radii", lo_t, hi_t, fill ? "" : " um",
                error, m_grain.table.nodes, GrainTableTolerance, GrainTableRecords);
        m_grain_table_lo = lo_t;
        m_grain_table_hi = hi_t;
        // a mean albedo for the sampling weights only: at the middle of the range
        double r_mid = fill ? 0.5 * (lo + hi) : std::sqrt(lo * hi), rho = 0.0;
        for (size_t i = 0; i < m_table_wavelengths.size(); ++i) {
            auto [qe, qs] = powder::efficiency_at(m_grain.table, i, r_mid);
            rho += qs / qe;
        }
        m_grain_rho_mean = rho / (double) m_table_wavelengths.size();
        // the constant-radius tables are not used; keep them valid for packing
        FloatStorage zeros = dr::zeros<FloatStorage>(m_table_wavelengths.size());
        m_mie = { zeros, zeros, zeros, zeros, zeros };
    }

    /// The albedo of spatially varying grains per lane (docs/model.md; slab: Q_ext = 1,
    /// Q_sca = rho)
    UnpolarizedSpectrum grain_texture_albedo(const SurfaceInteraction3f &si,
                                             Mask active) const {
        Float r1 = at(table_param(), si, active);
        if (!m_two_populations)
            return Tables::grain_albedo(m_grain, r1, nullptr, nullptr, si, active);
        Float r2 = at(powder_param::Radius2, si, active),
              f2 = at(powder_param::Fraction2, si, active);
        return Tables::grain_albedo(m_grain, r1, &r2, &f2, si, active);
    }

    // grain tables (powder_tables.h), at the table wavelengths
    std::vector<double> m_table_wavelengths;       ///< nm
    std::vector<std::complex<double>> m_index;     ///< n + i k at those wavelengths
    typename Tables::MieTables m_mie;
    FloatStorage m_tau_table;
    bool m_tau_table_constant = false;     ///< every entry of m_tau_table is the same
    FloatStorage m_packed;                 ///< spectral: records for lookup_grains
    /// RGB and mono: the entries of the albedo and tau_o tables, one per channel
    UnpolarizedSpectrum m_rho_channels = 0.f, m_tau_channels = 0.f;
    typename Tables::FresnelIndex m_fresnel; ///< surface_fresnel
    /// spatially varying grains: the efficiency table (grain_texture_albedo), the
    /// values it covers and the agglomerate property it holds
    typename Tables::GrainTexture m_grain;
    double m_grain_table_lo = 0.0, m_grain_table_hi = 0.0, m_grain_table_held = 0.0;
    double m_grain_rho_mean = 0.5;
};

NAMESPACE_END(mitsuba)
