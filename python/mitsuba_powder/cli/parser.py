"""The argument parser of ``mitsuba-powder``: one ``_add_<command>_parser`` per command."""

from __future__ import annotations

import argparse

from ..fitting.optimise import DEFAULT_STARTS, GLOBAL_STAGES, NLOPT_EVALUATIONS_PER_START
from ..plugin import registry
from .appearance import _cmd_albedo, _cmd_colour, _cmd_unmix
from .fitting import _cmd_compare_models, _cmd_fit, _cmd_simulate
from .rendering import _cmd_compare_photo, _cmd_info, _cmd_render, _cmd_render_gonio
from .rti import _cmd_compare_maps, _cmd_fit_maps, _cmd_relight

#: The values of fit-maps' choice options as its help shows them (checked by the fit:
#: tests/rti/test_rti_options.py compares them with mitsuba_powder.rti's)
GAIN_MODES = "{fit,fixed}"
GAIN_MODEL_MODES = "{none,free,smooth}"
SOLVER_NAMES = "{drjit,numpy}"


class _HelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the help already states it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or not action.option_strings or action.default is None
                or action.default is argparse.SUPPRESS or isinstance(action.default, bool)
                or action.default == []):
            return text
        return text + " (default: %(default)s)"


def _version() -> str:
    """This package's version and the mitsuba and drjit releases it was built for."""
    from .._versions import version_text

    return version_text()


def _add_set_option(p: argparse.ArgumentParser, text: str) -> None:
    """The repeatable ``--set NAME=VALUE`` option (a plugin property)."""
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=text)


def _add_capture_options(p: argparse.ArgumentParser, use: str) -> None:
    """The capture argument and its options (commands that read RTI captures)."""
    p.add_argument("capture", help="the capture's .lp file (first line the count, then "
                                   "'filename lx ly lz'); images beside it")
    p.add_argument("--encoding", choices=("srgb", "linear"), default="srgb",
                   help="srgb: file values are sRGB-encoded (linearised on read); linear: "
                        "value / full scale is linear (default srgb)")
    p.add_argument("--mask", default=None,
                   help=f"mask image (PNG): pixels above half scale are {use}")
    p.add_argument("--saturation", default=None, metavar="LEVEL",
                   help="observations with a channel at or above this linear level are left "
                        "out of the powder fit (> 0; default 0.99 of full scale)")
    _add_light_options(p)


def _add_light_options(p: argparse.ArgumentParser, fit: bool = True) -> None:
    """The lights' distance and the unit of .lp light positions (docs/rti.md, "Near-field
    lights")."""
    p.add_argument("--light-distance", default=None, metavar="R",
                   help="distance of the lights from the image's centre in image widths "
                        "(> the image's half-diagonal), 'inf' (distant lights)"
                        + (", or 'fit' (one distance fitted with the gains)" if fit else "")
                        + "; default inf for an .lp of unit directions, the positions for an "
                          ".lp of light positions")
    p.add_argument("--pixel-size", type=float, default=None, metavar="P",
                   help="size of a pixel in the unit of the .lp light positions (an .lp of "
                        "positions needs it: the image is P x width wide)")


def _add_data_options(p: argparse.ArgumentParser) -> None:
    """Options of the commands that read measurement files."""
    p.add_argument("--convention", choices=("signed", "physical"), default=None,
                   help="IPAG files: angle convention (default: decided from the file; "
                        "see docs/fitting.md, 'Files from IPAG goniometers and SSHADE')")
    p.add_argument("--zero-error", choices=("raise", "unweighted", "skip"), default="raise",
                   help="IPAG files where some errors are zero or missing: stop (raise), "
                        "fit unweighted, or skip those values")


def _add_info_parser(sub: argparse._SubParsersAction) -> None:
    """The ``info`` command."""
    p = sub.add_parser("info", help="show where the plugin is and whether LLVM works")
    p.set_defaults(func=_cmd_info)


def _add_render_parser(sub: argparse._SubParsersAction) -> None:
    """The ``render`` command."""
    p = sub.add_parser("render", help="render a scene file that uses the powder BSDF")
    p.add_argument("scene", help="scene XML file")
    p.add_argument("-o", "--output", required=True, help="output image (.exr or .png)")
    p.add_argument("--variant", default="scalar_rgb", help="Mitsuba variant (default scalar_rgb)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: scene's)")
    p.add_argument(
        "-D", "--define", action="append", default=[], metavar="NAME=VALUE",
        help="set a scene parameter declared with <default name=...> (repeatable)",
    )
    p.add_argument("--params", default=None,
                   help="JSON of powder properties or a fit.json, set on every powder BSDF")
    _add_set_option(p, "a powder property set on every powder BSDF (repeatable); a name that "
                    "is not a powder property is an error")
    p.add_argument("--allow-missing", action="store_true",
                   help="render even if some --params/--set properties cannot be set on this "
                        "scene (default: an error naming them)")
    p.set_defaults(func=_cmd_render)


def _add_render_gonio_parser(sub: argparse._SubParsersAction) -> None:
    """The ``render-gonio`` command."""
    p = sub.add_parser("render-gonio",
                       help="render the patch at gonio geometries; rendered vs analytic BRF")
    p.add_argument("--protocol", default=None,
                   help="comma-separated protocols: shadows, backscatter (default both)")
    p.add_argument("--data", default=None,
                   help="measurement CSV, IPAG file or folder: render its geometries and "
                        "wavelengths (mono)")
    p.add_argument("--params", default=None, help="JSON of plugin properties or a fit.json")
    _add_set_option(p, "plugin property (repeatable), e.g. --set extinction=2")
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default llvm_ad_rgb; llvm_ad_mono with --data)")
    p.add_argument("--wavelength", type=float, default=None,
                   help="nm: with --protocol, the mono variants' wavelength (default 700); "
                        "with --data, render only that wavelength's rows")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel")
    p.add_argument("--resolution", type=int, default=16, help="pixels per side per geometry")
    p.add_argument("--source-radius", type=float, default=0.0,
                   help="angular radius of the source, degrees (0: collimated)")
    p.add_argument("--strategy", default="emitter", choices=("emitter", "bsdf", "mis"),
                   help="how the source is sampled: emitter, bsdf or multiple importance "
                        "sampling")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="gonio_out", help="output folder")
    _add_data_options(p)
    p.set_defaults(func=_cmd_render_gonio, out_folder=True)


def _add_compare_photo_parser(sub: argparse._SubParsersAction) -> None:
    """The ``compare-photo`` command."""
    p = sub.add_parser("compare-photo", help="compare a render with a photo (CIEDE2000)")
    p.add_argument("render", help="rendered image (.exr, .png, .jpg)")
    p.add_argument("photo", help="photograph (.exr, .png, .jpg; 8 or 16 bit)")
    for who in ("render", "photo"):
        p.add_argument(f"--{who}-encoding", default="auto", choices=("auto", "linear", "srgb"),
                       help="auto: EXR linear, PNG/JPEG sRGB-encoded")
    p.add_argument("--chart", default=None, metavar="'X,Y X,Y X,Y X,Y'",
                   help="calibrate the photo with the ColorChecker 24 in it: pixel centres of "
                        "its dark skin, bluish green, black and white patches")
    p.add_argument("--chart-window", type=int, default=3,
                   help="half-size of the patch sampling window, px")
    p.add_argument("--align", default="white-balance",
                   choices=("none", "exposure", "white-balance"),
                   help="exposure: one gain; white-balance: per-channel gains")
    p.add_argument("--region", default=None, help="x0,y0,x1,y1: pixels to compare")
    p.add_argument("--white", type=float, default=None,
                   help="linear level of L* = 100 (default: the render's 99th percentile)")
    p.add_argument("--saturation", type=float, default=None,
                   help="leave out photo pixels with a channel >= this linear value (default "
                        "0.99 for PNG/JPEG, none for EXR; negative: keep all)")
    p.add_argument("--max-clipped", type=float, default=0.1, metavar="FRACTION",
                   help="stop with an error when more than this fraction of the compared "
                        "region is clipped in the photo (0-1; 1: never)")
    p.add_argument("--out", default="photo_compare",
                   help="output folder (photo_comparison.json, delta_e.png, side_by_side.png)")
    p.set_defaults(func=_cmd_compare_photo, out_folder=True)


def _add_albedo_parser(sub: argparse._SubParsersAction) -> None:
    """The ``albedo`` command."""
    p = sub.add_parser("albedo", help="the albedo spectrum that reproduces a measured "
                                      "reflectance or an sRGB colour")
    p.add_argument("--reflectance", default=None, metavar="FILE.csv",
                   help="CSV of wavelength (nm), reflectance")
    p.add_argument("--srgb", default=None, metavar="R,G,B",
                   help="an sRGB colour (0-1 or 0-255), upsampled to a spectrum")
    p.add_argument("--geometry", default="0:d",
                   help="0:d (directional-hemispherical at normal incidence) or "
                        "THETA_I:THETA_O, e.g. 0:45 (the BRF in the plane of incidence)")
    _add_set_option(p, "another plugin property, e.g. --set extinction=0.5 (repeatable)")
    p.add_argument("--out", required=True, help="output spectrum file (.spd)")
    p.set_defaults(func=_cmd_albedo)


def _add_unmix_parser(sub: argparse._SubParsersAction) -> None:
    """The ``unmix`` command."""
    p = sub.add_parser("unmix", help="fractions of a pigment mixture from an albedo spectrum "
                                     "(docs/fitting.md, Unmixing)")
    p.add_argument("albedo", help="CSV: wavelength (nm), single-scattering albedo, its "
                                  "standard uncertainty (e.g. from fit with the albedo free); "
                                  "with --baseline: wavelength, reflectance, its uncertainty")
    p.add_argument("--mix", required=True,
                   help="the materials, start fractions and radii: material:fraction:radius,... "
                        "(2 to 4), e.g. kaolinite:80%%:1um,hematite:10%%:0.1um,"
                        "magnetite:10%%:0.3um; population 1 (the first) must be present")
    p.add_argument("--by", default="volume", choices=["mass", "volume"],
                   help="how the --mix start fractions are given (default volume)")
    p.add_argument("--free-radii", action="store_true", help="fit the radii too")
    _add_global_options(p, baseline=True)
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the Sobol scrambling or of nlopt, in [0, 2^32) (default 0)")
    p.add_argument("--baseline", default=None, choices=["hapke", "km", "all"],
                   help="read the CSV as a reflectance spectrum (wavelength, reflectance, its "
                        "standard uncertainty) and unmix it with Hapke's intimate-mixture rule, "
                        "two-constant Kubelka-Munk, or both beside the powder model (all: "
                        "needs --set tau_o=...) (docs/colour.md, Unmixing against the "
                        "baselines)")
    p.add_argument("--endmembers", default=None, metavar="A.csv,B.csv,...",
                   help="with --baseline: each pure material's reflectance (wavelength, "
                        "reflectance), in the order of --mix")
    p.add_argument("--tints", default=None, metavar="T2.csv:10%,...",
                   help="with --baseline km or all: a tint of each pigment 2..n with the white "
                        "(population 1) and the pigment's mass fraction in it (default: S = 1 "
                        "for every pigment)")
    p.add_argument("--geometry", default=None,
                   help="with --baseline: the reflectance's geometry, 0:d or THETA_I:THETA_O "
                        "(default 0:d)")
    _add_set_option(p, "with --baseline all: a plugin property of the powder row, e.g. "
                       "--set tau_o=2 (repeatable)")
    p.add_argument("--json", default=None, help="write the result as JSON")
    p.set_defaults(func=_cmd_unmix)


def _add_global_options(p: argparse.ArgumentParser, baseline: bool = False) -> None:
    """``--global`` and ``--starts`` of ``fit`` and ``unmix`` (docs/fitting.md, "The global
    stage"); ``baseline``: unmix's, which --baseline refuses (their defaults are then left
    unset, so that the command sees whether they were given)."""
    note = "; not with --baseline" if baseline else ""
    p.add_argument("--global", dest="global_stage", choices=GLOBAL_STAGES,
                   default=None if baseline else "sobol",
                   help="the global stage: sobol (Sobol starts, batched Levenberg-Marquardt; "
                        "the default), mlsl or crs2 (nlopt, then the same Levenberg-Marquardt "
                        f"steps; needs nlopt){note}")
    p.add_argument("--starts", type=int, default=None if baseline else DEFAULT_STARTS,
                   help="starts of the global phase (Sobol design; with the radius free, on a "
                        f"log grid of radii); mlsl and crs2: {NLOPT_EVALUATIONS_PER_START} "
                        "model evaluations per start"
                        + (f" (>= 1, default {DEFAULT_STARTS}){note}" if baseline else ""))


def _add_colour_parser(sub: argparse._SubParsersAction) -> None:
    """The ``colour`` command."""
    p = sub.add_parser("colour", help="albedo, tau_o and colour of a powder from its grains")
    p.add_argument("--radius", type=float, default=None,
                   help=f"grain radius, um (default {registry.DEFAULTS['radius']:g})")
    p.add_argument("--radius2", type=float, default=None, help="second population radius, um")
    p.add_argument("--fraction2", type=float, default=None,
                   help="volume fraction of the second population")
    p.add_argument("--material", default=None,
                   help=f"{', '.join(registry.MATERIALS)} or a refractiveindex.info YAML file "
                        f"(default {registry.DEFAULTS['material']})")
    p.add_argument("--grains", default=registry.DEFAULTS["grains"],
                   choices=list(registry.GRAIN_MODELS),
                   help="grain model (docs/powder.md, Grain models)")
    p.add_argument("--agglomerate-radius", type=float, default=None,
                   help="agglomerate radius, um (--grains agglomerate)")
    p.add_argument("--agglomerate-fill", type=float, default=None,
                   help="volume fill of crystallites in an agglomerate (default "
                        f"{registry.DEFAULTS['agglomerate_fill']:g})")
    p.add_argument("--mixing", default=None, choices=["bruggeman", "maxwell_garnett"],
                   help="effective-medium rule of an agglomerate (default bruggeman)")
    p.add_argument("--mix", default=None,
                   help="a pigment mixture instead of --material/--radius/--radius2/"
                        "--fraction2: material:fraction:radius,... (up to 4), e.g. "
                        "hematite:5%%:0.1um,kaolinite:95%%:1um; fractions sum to 1")
    p.add_argument("--by", default="volume", choices=["mass", "volume"],
                   help="how the --mix fractions are given (mass: converted with the "
                        "materials' densities; default volume)")
    p.add_argument("--samples", type=int, default=4096, help="quadrature nodes")
    p.set_defaults(func=_cmd_colour)


def _add_fit_parser(sub: argparse._SubParsersAction) -> None:
    """The ``fit`` command."""
    p = sub.add_parser("fit", help="fit the powder model to goniometer measurements")
    p.add_argument("data", help="measurement CSV, IPAG file, or folder of IPAG "
                   "single-geometry files (see mitsuba_powder.io.measurements)")
    p.add_argument("--wavelength", type=float, nargs="+", default=None,
                   help="fit only these wavelengths, nm (several: a joint fit)")
    p.add_argument("--free", default=None,
                   help="plugin properties to fit, comma-separated (default: amplitude_volume,"
                        "g,extinction,amplitude_surface,correlation_length, plus radius when "
                        "several wavelengths are fitted)")
    _add_set_option(p, "a fixed plugin property, e.g. --set tau_o=0.6667 (repeatable)")
    p.add_argument("--fit-incidences", default=None, metavar="DEG,DEG,...",
                   help="fit only these incidences and report the prediction of the others")
    _add_global_options(p)
    p.add_argument("--polish", type=int, default=4,
                   help="distinct end points of the global phase polished (scipy)")
    p.add_argument("--regime", choices=("ebs", "free"), default="ebs",
                   help="ebs: bound the extinction so that kappa/k0 <= 0.25 at every fitted "
                        "wavelength (the narrow-cone regime of the theory); free: lift it")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="fit_out", help="output folder (fit.json, figures)")
    p.add_argument("--figures", choices=("summary", "all", "none"), default="summary",
                   help="summary: one set for the whole fit (relative RMSE per wavelength, "
                        "residuals against the angles, the plane of incidence at up to 4 "
                        "wavelengths); all: also a plane-of-incidence and a polar figure per "
                        "wavelength; none: fit.json only (default summary)")
    _add_data_options(p)
    p.set_defaults(func=_cmd_fit, out_folder=True)


def _add_simulate_parser(sub: argparse._SubParsersAction) -> None:
    """The ``simulate`` command."""
    p = sub.add_parser("simulate", help="simulate measurements at protocol geometries")
    p.add_argument("--params", required=True,
                   help="JSON of plugin properties, or a fit.json (its 'parameters')")
    p.add_argument("--protocol", default="shadows,backscatter",
                   help="comma-separated: shadows, backscatter")
    p.add_argument("--wavelength", type=float, nargs="+", default=None, help="nm (700)")
    p.add_argument("--noise", type=float, default=0.0, help="relative 1-sigma noise")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True,
                   help="output CSV, IPAG file (--layout multi) or folder (--layout single)")
    p.add_argument("--format", choices=("csv", "ipag"), default="csv",
                   help="csv (project format) or ipag (IPAG goniometer text)")
    p.add_argument("--layout", choices=("multi", "single"), default="multi",
                   help="ipag: one multi-geometry file, or a folder of single-geometry files")
    p.add_argument("--convention", choices=("physical", "signed"), default="physical",
                   help="ipag: angles as newer files and SSHADE (physical) or older files "
                        "(signed; plane of incidence only)")
    p.add_argument("--sample", default="synthetic", help="ipag: sample name in the file")
    p.set_defaults(func=_cmd_simulate)


def _add_compare_models_parser(sub: argparse._SubParsersAction) -> None:
    """The ``compare-models`` command."""
    p = sub.add_parser("compare-models",
                       help="fit the powder model and four baselines to the same data")
    p.add_argument("data", help="measurement CSV, IPAG file or folder")
    p.add_argument("--wavelength", type=float, nargs="+", default=None, help="nm")
    p.add_argument("--free", default=None, help="powder properties to fit (as in fit)")
    _add_set_option(p, "fixed powder property (repeatable)")
    p.add_argument("--starts", type=int, default=64,
                   help="starts of each model's global phase")
    p.add_argument("--out", default="model_compare",
                   help="output folder (model_comparison.md and .json)")
    _add_data_options(p)
    p.set_defaults(func=_cmd_compare_models, out_folder=True)


def _add_fit_maps_parser(sub: argparse._SubParsersAction) -> None:
    """The ``fit-maps`` command."""
    p = sub.add_parser("fit-maps", help="fit a normal and powder parameters to every pixel of "
                                        "an RTI capture; write EXR maps and a scene")
    p.add_argument("--out", required=True,
                   help="output folder: <property>.exr, albedo.exr, normal.exr, residual.exr, "
                        "fit.json, scene.xml")
    _add_capture_options(p, "fitted")
    _add_fit_options(p)
    _add_shadow_options(p)
    _add_tile_options(p)
    p.set_defaults(func=_cmd_fit_maps, out_folder=True)


def _add_fit_options(p: argparse.ArgumentParser, model: str = "") -> None:
    """The per-pixel powder fit's options, shared by fit-maps and compare-maps (``model``:
    how compare-maps' help introduces them). The values are checked by the fit
    (mitsuba_powder.rti.options), not here."""
    p.add_argument("--free", default=None,
                   help=model + "comma-separated properties fitted per pixel besides the "
                        "normal (default: chosen per capture by cross-validation over "
                        "held-out lights: albedo alone or albedo, amplitude_surface, "
                        "correlation_length; docs/rti.md says why)")
    p.add_argument("--gains", default="fixed", metavar=GAIN_MODES,
                   help=model + "per-light gains shared by all pixels: fixed (default: all "
                        "the exposure, or the --reference card's irradiances) or fit (fitted "
                        "with the maps, their mean the exposure)")
    p.add_argument("--exposure", default=None, metavar="E",
                   help=model + "the lights' irradiance scale (> 0), or 'fit'; default: "
                        "fitted (a scan and a polish on a subsample), or from --reference")
    p.add_argument("--reference", default=None, metavar="x0,y0,x1,y1[:REFLECTANCE]",
                   help=model + "a white or grey card in the frame (pixels x0 <= x < x1, "
                        "y0 <= y < y1 from the top left; reflectance, default 0.99): each "
                        "light's irradiance and the exposure; its pixels are not fitted")
    _add_set_option(p, model + "a plugin property held for every pixel (repeatable), e.g. "
                    "--set extinction=0.5")
    p.add_argument("--iterations", default=30, metavar="N",
                   help=model + "Levenberg-Marquardt iterations per round")
    p.add_argument("--rounds", default=3, metavar="N",
                   help=model + "alternations of the per-pixel fit with the gains and the "
                                "shadow flags")
    p.add_argument("--gain-model", default="none", metavar=GAIN_MODEL_MODES,
                   help=model + "none: a light not fitted has the exposure as its gain; "
                        "free: each fitted light keeps its gain, a light not fitted gets the "
                        "smooth trend of the gains in its direction; smooth: the gains are "
                        "the trend (with residuals of relative spread --gain-spread)")
    p.add_argument("--gain-degree", default=2, metavar="D",
                   help=model + "degree of the gains' trend, a polynomial in "
                                "sin(elevation) (0-6)")
    p.add_argument("--gain-spread", default=None, metavar="TAU",
                   help=model + "smooth gains: relative spread of the lights about the trend "
                        "(e.g. 0.02); default none (the gains are the trend)")
    p.add_argument("--gain-pixels", default=None, metavar="N", help=model + "pixels of the "
                   "whole capture the gains are fitted on (--gains fit), then held for every "
                   "pixel (>= 1; default 16384)")
    p.add_argument("--memory-gb", default=None, metavar="GB", help=model + "working memory "
                   "of the fit besides the images, GiB (> 0; default an eighth of this "
                   "machine's, at most 1.5): pixels are fitted in blocks that fit in it")
    p.add_argument("--solver", default="drjit", metavar=SOLVER_NAMES,
                   help=model + "per-pixel solver: drjit (normal equations in Dr.Jit "
                        "kernels, default) or numpy (the reference)")


def _add_shadow_options(p: argparse.ArgumentParser, who: str = "") -> None:
    """The fit's cast shadows (docs/rti.md, "Relief and cast shadows")."""
    p.add_argument("--shadows", default=None, metavar="{auto,relief,ratio}",
                   help=f"{who}auto (default): integrate the relief from the fitted normals "
                        "and keep its cast shadows where they relight held-out lights better "
                        "(cross-validated over folds of the lights on a subsample of pixels, "
                        "on the pixels it shades; the choice in fit.json); relief: always "
                        "(the pixels it shades fitted again under each light's visibility "
                        "over the relief); ratio: no relief in "
                        "the fit, observations far below the model flagged only (tiled fits: "
                        "always ratio)")
    if not who:
        _add_light_size(p)


def _add_light_size(p: argparse.ArgumentParser, who: str = "") -> None:
    """``--light-size``: the soft edge of cast shadows (``who``: the rows it applies to)."""
    p.add_argument("--light-size", default=None, metavar="DEG",
                   help=f"{who}the lights' angular radius, degrees (0-45; default 0.5): the "
                        "soft edge of cast shadows")


def _add_render_options(p: argparse.ArgumentParser, what: str) -> None:
    """Rendered relights: samples per pixel and the Mitsuba variant."""
    p.add_argument("--spp", default=64, metavar="N",
                   help=f"{what}: samples per pixel (>= 1; default 64)")
    p.add_argument("--render-variant", default="llvm_ad_rgb", metavar="VARIANT",
                   help=f"{what}: the Mitsuba variant (any RGB variant: scalar_rgb, "
                        "llvm_ad_rgb, cuda_ad_rgb; default llvm_ad_rgb)")


def _add_tile_options(p: argparse.ArgumentParser) -> None:
    """fit-maps' tiled fit on a Dask cluster (docs/rti.md, "Tiles and clusters"). The values
    are checked by the fit (mitsuba_powder.rti.options), not here."""
    p.add_argument("--tile-size", default=None, metavar="PX", help="fit in square tiles of "
                   "PX pixels (>= 8) on a Dask cluster, the gains fitted first on --gain-pixels "
                   "pixels and held; default: one fit of the whole capture in this process")
    p.add_argument("--workers", default=None, metavar="N", help="tiled: worker processes of "
                   "the local cluster (>= 1; default one per core)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT", help="tiled: an "
                   "existing Dask cluster's scheduler (its workers read the images from the "
                   "same path)")
    p.add_argument("--resume", action="store_true",
                   help="tiled: keep the tiles already in OUT/tiles (of the same settings)")


def _add_relight_parser(sub: argparse._SubParsersAction) -> None:
    """The ``relight`` command."""
    p = sub.add_parser("relight", help="images of a fit-maps result under the lights of an "
                                       ".lp file")
    p.add_argument("maps", help="folder written by fit-maps")
    p.add_argument("--lp", required=True,
                   help="lights: an .lp file (count, then 'filename lx ly lz' per line)")
    p.add_argument("--out", required=True, help="output folder (one image per .lp line, "
                                                "the capture's format and bit depth)")
    _add_light_options(p, fit=False)
    p.add_argument("--render", action="store_true",
                   help="path trace scene.xml (the relief's mesh with the powder BSDF: cast "
                        "shadows and interreflections) under each light instead of the "
                        "per-pixel model")
    shadows = p.add_mutually_exclusive_group()
    shadows.add_argument("--shadows", action="store_true",
                         help="per-pixel model: cast shadows over the fit's relief "
                              "(relief.exr) even where the fit did not use them (default: "
                              "when the fit used them, fit.json's fit.shadows = relief: "
                              "--shadows relief, or auto where it chose the relief)")
    shadows.add_argument("--no-shadows", action="store_true",
                         help="per-pixel model: no cast shadows even where the fit used them")
    _add_render_options(p, "--render")
    p.set_defaults(func=_cmd_relight, out_folder=True)


def _add_compare_maps_parser(sub: argparse._SubParsersAction) -> None:
    """The ``compare-maps`` command."""
    p = sub.add_parser("compare-maps", help="held-out-light error of per-pixel models (PTM, "
                                            "HSH, Lambertian) on an RTI capture")
    p.add_argument("--out", required=True,
                   help="output folder (compare.md, compare.json, error maps)")
    _add_capture_options(p, "scored")
    p.add_argument("--models", default="ptm,hsh,lambertian,lambertian_clamped",
                   help="comma-separated: ptm, hsh, lambertian, lambertian_clamped, powder "
                        "(the per-pixel powder fit of fit-maps with --shadows, default auto, "
                        "relit as relight does), powder_shadows (the fit with its relief's "
                        "cast shadows always, --shadows relief), powder_rendered (that fit's "
                        "relief path traced by Mitsuba)")
    _add_shadow_options(p, "powder row: ")
    _add_light_size(p, "powder rows with a relief: ")
    _add_render_options(p, "powder_rendered")
    _add_fit_options(p, "powder model: ")
    p.add_argument("--phase", type=int, default=4,
                   help="interpolation protocol: hold out the lights k %% 5 == PHASE (.lp "
                        "order from 0; default 4)")
    p.add_argument("--no-error-images", action="store_true",
                   help="do not write the per-pixel error maps (PNG)")
    p.add_argument("--field", choices=("far", "near", "both"), default=None,
                   help="score each model with distant lights (far), lights at the light "
                        "distance (near, rows <model>_near) or both (default: both when a "
                        "finite light distance is given or fitted, else far)")
    p.set_defaults(func=_cmd_compare_maps, out_folder=True)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mitsuba-powder",
        description="Dry-powder reflectance (Gerardin et al. 2023) for Mitsuba 3.",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    _add_info_parser(sub)
    _add_render_parser(sub)
    _add_albedo_parser(sub)
    _add_colour_parser(sub)
    _add_unmix_parser(sub)
    _add_fit_parser(sub)
    _add_simulate_parser(sub)
    _add_compare_models_parser(sub)
    _add_render_gonio_parser(sub)
    _add_compare_photo_parser(sub)
    _add_compare_maps_parser(sub)
    _add_fit_maps_parser(sub)
    _add_relight_parser(sub)
    for command in sub.choices.values():
        command.formatter_class = _HelpFormatter
    return parser
