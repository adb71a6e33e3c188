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
        // each material's index; throws (naming both) if a wavelength is outside its table
        material_index.assign(p.materials.size(), {});
        for (size_t mi = 0; mi < p.materials.size(); ++mi)
            for (double wl : table_wavelengths)
                material_index[mi].push_back(p.materials[mi].eval(wl * 1e-3));
        for (size_t i = 0; i < table_wavelengths.size(); ++i) {
            powder::PopulationIndex m;
            for (size_t j = 0; j < m.size(); ++j)
                m[j] = material_index[p.material_of[j]][i];
            population_index.push_back(m);
        }
        grain_index = mixture_index(p, p.fractions());
        if (!p.albedo)
            warn_crystallite_size(p);
        update_index_tables(p);
    }

    /// Whether the populations are of different materials (then tau_o and the surface
    /// Fresnel index depend on the fractions)
    static bool mixed(const Params &p) { return !p.albedo && p.materials.size() > 1; }

    /// The index of the grains at the table wavelengths: the material's, or for populations
    /// of different materials the Bruggeman index of the mixture at the fractions `f`
    /// (docs/model.md, "The mixture's index for tau_o")
    std::vector<std::complex<double>>
    mixture_index(const Params &p, const std::array<double, powder_param::MaxPopulations> &f) const {
        if (!mixed(p))
            return material_index[0];
        powder::Grains g;
        g.populations = p.populations;
        g.set_fractions(f);
        std::vector<double> w(g.f.begin(), g.f.begin() + p.populations);
        std::vector<std::complex<double>> out;
        for (const powder::PopulationIndex &m : population_index)
            out.push_back(powder::bruggeman_mixture(
                std::vector<std::complex<double>>(m.begin(), m.begin() + p.populations), w));
        return out;
    }

    /// tau_o (Fresnel) and the surface Fresnel index from grain_index; for a mixture with
    /// gradients tracked on a fraction, d tau_o / d f_j (a difference of step 1e-6) as
    /// tangents
    void update_index_tables(const Params &p) {
        if (!p.tau_given) {
            auto tau_of = [](const std::vector<std::complex<double>> &index) {
                std::vector<ScalarFloat> tau;
                for (const auto &m : index)
                    tau.push_back((ScalarFloat) powder::tau_o_fresnel(m.real()));
                return tau;
            };
            std::vector<ScalarFloat> tau = tau_of(grain_index);
            tau_table = Tables::upload(tau);
            tau_table_constant =
                std::all_of(tau.begin(), tau.end(), [&](ScalarFloat t) { return t == tau[0]; });
            if constexpr (dr::is_diff_v<Float>) {
                if (mixed(p))
                    for (size_t j = 1; j < p.populations; ++j) {
                        const Float &fj = p[powder_param::PopulationFraction[j]];
                        if (!dr::grad_enabled(fj))
                            continue;
                        auto f = p.fractions();
                        const double h = 1e-6;
                        f[j] += f[j] + h <= 1.0 ? h : -h;
                        double step = f[j] - p.fractions()[j];
                        std::vector<double> t1(tau.size());
                        std::vector<std::complex<double>> index = mixture_index(p, f);
                        std::vector<ScalarFloat> d(tau.size());
                        for (size_t i = 0; i < tau.size(); ++i)
                            d[i] = (ScalarFloat) ((powder::tau_o_fresnel(index[i].real()) -
                                                   powder::tau_o_fresnel(grain_index[i].real())) /
                                                  step);
                        tau_table = tau_table + Tables::upload(d) * (fj - dr::detach(fj));
                    }
                dr::make_opaque(tau_table);
            }
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
        if (mixed(p) && grains_changed && !keys.empty()) {
            grain_index = mixture_index(p, p.fractions());
            update_index_tables(p);
        }
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
        powder::Grains g;
        g.populations = p.agglomerate() ? 1 : p.populations;
        for (size_t j = 0; j < g.populations; ++j)
            g.r[j] = Params::value_of(p[powder_param::PopulationRadius[j]]);
        if (p.agglomerate())
            g.r[0] = Params::value_of(p.radius);
        g.set_fractions(p.fractions());
        g.model = p.grain_model;
        g.agglomerate_radius = Params::value_of(p.agglomerate_radius);
        g.agglomerate_fill = Params::value_of(p.agglomerate_fill);
        g.mixing = p.mixing;
        return g;
    }

    /// The Mie tables; rho's derivatives are attached as tangents when gradients are
    /// tracked on a grain parameter
    void update_mie_tables(const Params &p) {
        std::vector<std::pair<const Float *, powder_param::Id>> params;
        for (size_t i = 0; i < powder_param::Count; ++i) {
            powder_param::Id id = (powder_param::Id) i;
            if (powder_param::is_grain_param(id) && p.in_use(id))
                params.emplace_back(&p[id], id);
        }
        bool tangents = false;
        if constexpr (dr::is_diff_v<Float>)
            for (auto &gp : params)
                tangents |= dr::grad_enabled(*gp.first);
        if (!tangents)
            params.clear();
        mie = Tables::mie_tables(constant_grains(p), table_wavelengths, population_index, params);
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
        // one table per material, over the radii of its populations (agglomerates: one)
        size_t tables = p.agglomerate() ? 1 : p.materials.size();
        for (size_t mi = 0; mi < tables; ++mi) {
            double lo = std::numeric_limits<double>::infinity(), hi = -lo;
            const char *name = powder_param::Table[p.table_param()].name;
            if (p.agglomerate()) {
                std::tie(lo, hi) = p.value_range(p.table_param());
            } else {
                for (size_t j = 0; j < p.populations; ++j) {
                    if (p.material_of[j] != mi)
                        continue;
                    auto [l, h] = p.value_range(powder_param::PopulationRadius[j]);
                    lo = std::min(lo, l);
                    hi = std::max(hi, h);
                    if (l == lo)
                        name = powder_param::Table[powder_param::PopulationRadius[j]].name;
                }
            }
            GrainTable &t = grain_tables[mi];
            if (t.tex.table.nodes > 0 && lo >= t.lo && hi <= t.hi && held_value == t.held)
                continue; // the current table covers the values
            powder::Grains g;
            g.model = p.grain_model;
            g.mixing = p.mixing;
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
            build_grain_texture_table(p, g, mi, name, lo, hi, lo_t, hi_t,
                                      fill ? powder::TableAxis::Fill
                                           : powder::TableAxis::LogRadius);
            t.held = held_value;
        }
    }

    /// Build the grain texture table of material mi over [lo_t, hi_t] of its variable
    /// (covering the texture values [lo, hi]; `name` the property, for errors) and upload
    /// its records
    void build_grain_texture_table(const Params &p, const powder::Grains &grains, size_t mi,
                                   const char *name, double lo, double hi, double lo_t,
                                   double hi_t, powder::TableAxis axis) {
        bool fill = axis == powder::TableAxis::Fill;
        double error = 0.0;
        GrainTable &t = grain_tables[mi];
        t.tex = Tables::grain_texture(powder::efficiency_table(
            grains, lo_t, hi_t, table_wavelengths, material_index[mi], name,
            GrainTableTolerance, GrainTableRecords, error, DrJitParallelFor(), axis));
        if (error > GrainTableTolerance)
            Log(Warn, "powder: the albedo table of %s %g-%g%s is accurate to %.2g "
                      "(relative, at the midpoints of its %zu nodes), not %g: the values "
                      "span too many Mie resonances for %zu records; narrow the texture's "
                      "range", fill ? "fills" : "radii", lo_t, hi_t, fill ? "" : " um",
                error, t.tex.table.nodes, GrainTableTolerance, GrainTableRecords);
        t.lo = lo_t;
        t.hi = hi_t;
        if (mi == 0) {
            // a mean albedo for the sampling weights only: at the middle of the range
            double r_mid = fill ? 0.5 * (lo + hi) : std::sqrt(lo * hi), rho = 0.0;
            for (size_t i = 0; i < table_wavelengths.size(); ++i) {
                auto [qe, qs] = powder::efficiency_at(t.tex.table, i, r_mid);
                rho += qs / qe;
            }
            grain_rho_mean = rho / (double) table_wavelengths.size();
        }
        // the constant-radius tables are not used; keep them valid for packing
        FloatStorage zero = dr::zeros<FloatStorage>(table_wavelengths.size());
        mie = { zero, zero, zero, zero, zero };
        DRJIT_MARK_USED(p);
    }

    /// The albedo of spatially varying grains per lane (docs/model.md; slab: Q_ext = 1,
    /// Q_sca = rho)
    UnpolarizedSpectrum grain_texture_albedo(const Params &p, const SurfaceInteraction3f &si,
                                             Mask active) const {
        if (p.agglomerate() || p.populations == 1) {
            Float r1 = p.at(p.table_param(), si, active);
            const typename Tables::GrainTexture *t = &grain_tables[0].tex;
            return Tables::grain_albedo(&t, &r1, &r1, 1, si, active);
        }
        const typename Tables::GrainTexture *t[powder_param::MaxPopulations];
        Float r[powder_param::MaxPopulations], f[powder_param::MaxPopulations];
        for (size_t j = 0; j < p.populations; ++j) {
            t[j] = &grain_tables[p.material_of[j]].tex;
            r[j] = p.at(powder_param::PopulationRadius[j], si, active);
            f[j] = j == 0 ? Float(1.f) : p.at(powder_param::PopulationFraction[j], si, active);
        }
        return Tables::grain_albedo(t, r, f, p.populations, si, active);
    }

    /// The efficiency table of one material's spatially varying grains, the values it
    /// covers and the agglomerate property it holds
    struct GrainTable {
        typename Tables::GrainTexture tex;
        double lo = 0.0, hi = 0.0, held = 0.0;
    };

    // grain tables (powder_tables.h), at the table wavelengths
    std::vector<double> table_wavelengths;         ///< nm
    std::vector<std::complex<double>> grain_index; ///< n + i k (of the mixture) there
    /// each material's index at those wavelengths, and each population's
    std::vector<std::vector<std::complex<double>>> material_index;
    std::vector<powder::PopulationIndex> population_index;
    typename Tables::MieTables mie;
    FloatStorage tau_table;
    bool tau_table_constant = false;     ///< every entry of tau_table is the same
    FloatStorage packed;                 ///< spectral: records for lookup
    /// RGB and mono: the entries of the albedo and tau_o tables, one per channel
    UnpolarizedSpectrum rho_channels = 0.f, tau_channels = 0.f;
    typename Tables::FresnelIndex fresnel; ///< surface_fresnel
    /// spatially varying grains: the efficiency table of each material
    /// (grain_texture_albedo)
    std::array<GrainTable, powder_param::MaxPopulations> grain_tables;
    double grain_rho_mean = 0.5;

    POWDER_TRAVERSE_MEMBERS(rho_channels, tau_channels, packed, mie, tau_table,
                            fresnel.records, grain_tables[0].tex.records,
                            grain_tables[1].tex.records, grain_tables[2].tex.records,
                            grain_tables[3].tex.records)
};

NAMESPACE_END(mitsuba)
