#pragma once

/*
 * Optical constants n + i k of a grain material against wavelength, for the `powder`
 * BSDF: loaded from refractiveindex.info YAML files by a strict loader (every row
 * checked), built from wavelength:value pairs, or averaged over the orientations of a
 * uniaxial crystal. Self-contained (no Mitsuba headers), as powder_optics.h.
 */

#include <algorithm>
#include <cmath>
#include <complex>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "powder_registry.h"

namespace powder {

/// Complex refractive index tabulated against wavelength (micrometres)
struct OpticalTable {
    std::vector<double> wavelength_um, n, k;
    std::string source;

    bool empty() const { return wavelength_um.empty(); }
    double min_um() const { return wavelength_um.front(); }
    double max_um() const { return wavelength_um.back(); }

    /// Linear interpolation; throws if `wl_um` lies outside the table
    std::complex<double> eval(double wl_um) const {
        if (!(wl_um >= min_um() && wl_um <= max_um()))
            fail("powder: wavelength ", wl_um * 1e3, " nm lies outside the optical constants of ",
                 source, ", which cover ", min_um() * 1e3, "-", max_um() * 1e3, " nm");
        size_t i = (size_t) (std::upper_bound(wavelength_um.begin(), wavelength_um.end(),
                                              wl_um) - wavelength_um.begin());
        i = std::min(std::max(i, (size_t) 1), wavelength_um.size() - 1);
        double t = (wl_um - wavelength_um[i - 1]) / (wavelength_um[i] - wavelength_um[i - 1]);
        return { n[i - 1] + t * (n[i] - n[i - 1]), k[i - 1] + t * (k[i] - k[i - 1]) };
    }
};

/// Parse one number; false if the token is not entirely a finite number
inline bool parse_number(const std::string &token, double &value) {
    char *end = nullptr;
    value = std::strtod(token.c_str(), &end);
    return end != token.c_str() && *end == '\0' && std::isfinite(value);
}

/// Append a row (wavelength in um, n, k), checking it; `where` names file and line
inline void append_row(OpticalTable &t, double wl, double n, double k, const std::string &where) {
    if (!(wl > 0.0))
        fail("powder: ", where, ": wavelength ", wl, " is not positive");
    if (!t.empty() && !(wl > t.wavelength_um.back()))
        fail("powder: ", where, ": wavelength ", wl, " um does not increase (previous row: ",
             t.wavelength_um.back(), " um); duplicate or out-of-order rows must be removed "
             "from the file");
    // the ranges of the properties eta and k (docs/model.md, "Valid ranges")
    if (!powder_param::EtaNumber.range.contains(n))
        fail("powder: ", where, ": n = ", n, " is out of range; valid range is ",
             powder_param::EtaNumber.range.str());
    if (!powder_param::KNumber.range.contains(k))
        fail("powder: ", where, ": k = ", k, " is out of range; valid range is ",
             powder_param::KNumber.range.str());
    t.wavelength_um.push_back(wl);
    t.n.push_back(n);
    t.k.push_back(k);
}

/**
 * Load a refractiveindex.info YAML file with a `tabulated nk` data block
 * (rows: wavelength in micrometres, n, k). Every row is checked; a malformed
 * row raises an error naming the file and the line.
 */
inline OpticalTable load_refractiveindex_yaml(const std::string &path) {
    std::ifstream is(path);
    if (!is.good())
        fail("powder: cannot open optical constants file \"", path, "\"");
    OpticalTable table;
    table.source = "\"" + path + "\"";
    std::string line;
    int lineno = 0, data_indent = -1;
    bool seen_type = false, in_data = false;
    while (std::getline(is, line)) {
        ++lineno;
        if (!line.empty() && line.back() == '\r')
            line.pop_back();
        size_t first = line.find_first_not_of(" \t");
        if (first == std::string::npos)
            continue;
        std::string body = line.substr(first);
        if (in_data) {
            if ((int) first > data_indent) {
                std::istringstream ss(body);
                std::vector<std::string> tokens;
                std::string tok;
                while (ss >> tok)
                    tokens.push_back(tok);
                std::string where = "\"" + path + "\", line " + std::to_string(lineno);
                double v[3];
                if (tokens.size() != 3 || !parse_number(tokens[0], v[0]) ||
                    !parse_number(tokens[1], v[1]) || !parse_number(tokens[2], v[2]))
                    fail("powder: ", where, ": expected three numbers (wavelength in um, n, k), "
                         "got \"", body, "\"");
                append_row(table, v[0], v[1], v[2], where);
                continue;
            }
            break; // end of the block
        }
        if (body.rfind("- type:", 0) == 0 || body.rfind("type:", 0) == 0) {
            std::string type = body.substr(body.find(':') + 1);
            type.erase(0, type.find_first_not_of(" \t"));
            if (type != "tabulated nk")
                fail("powder: \"", path, "\", line ", lineno, ": data of type \"", type,
                     "\" is not supported; only \"tabulated nk\" is");
            seen_type = true;
        } else if (seen_type && body.rfind("data:", 0) == 0) {
            in_data = true;
            data_indent = (int) first;
        }
    }
    if (!seen_type || table.wavelength_um.size() < 2)
        fail("powder: \"", path, "\" holds no \"tabulated nk\" data block with at least two "
             "rows");
    return table;
}

/// Table from wavelength/value pairs (nm) for eta and k given separately
inline OpticalTable table_from_pairs(const std::vector<double> &wl_nm_eta,
                                     const std::vector<double> &eta,
                                     const std::vector<double> &wl_nm_k,
                                     const std::vector<double> &k) {
    // union of the two wavelength grids, each interpolated linearly
    std::vector<double> grid(wl_nm_eta);
    grid.insert(grid.end(), wl_nm_k.begin(), wl_nm_k.end());
    std::sort(grid.begin(), grid.end());
    grid.erase(std::unique(grid.begin(), grid.end()), grid.end());
    auto interp = [](const std::vector<double> &x, const std::vector<double> &y, double t) {
        if (x.size() == 1)
            return y[0];
        size_t i = (size_t) (std::upper_bound(x.begin(), x.end(), t) - x.begin());
        i = std::min(std::max(i, (size_t) 1), x.size() - 1);
        double a = (t - x[i - 1]) / (x[i] - x[i - 1]);
        return y[i - 1] + a * (y[i] - y[i - 1]);
    };
    double lo = std::max(wl_nm_eta.front(), wl_nm_k.front()),
           hi = std::min(wl_nm_eta.back(), wl_nm_k.back());
    OpticalTable t;
    t.source = "the \"eta\" and \"k\" spectra";
    for (double w : grid)
        if (w >= lo && w <= hi)
            append_row(t, w * 1e-3, interp(wl_nm_eta, eta, w), interp(wl_nm_k, k, w),
                       "\"eta\"/\"k\" at " + std::to_string(w) + " nm");
    return t;
}

/// Orientation average of a uniaxial crystal: (2 o + e) / 3 on the o grid
inline OpticalTable orientation_average(const OpticalTable &o, const OpticalTable &e) {
    OpticalTable t;
    t.source = "orientation average (2 o + e) / 3 of " + o.source + " and " + e.source;
    for (size_t i = 0; i < o.wavelength_um.size(); ++i) {
        double wl = o.wavelength_um[i];
        if (wl < e.min_um() || wl > e.max_um())
            continue;
        std::complex<double> ce = e.eval(wl);
        append_row(t, wl, (2.0 * o.n[i] + ce.real()) / 3.0, (2.0 * o.k[i] + ce.imag()) / 3.0,
                   t.source);
    }
    return t;
}

} // namespace powder
