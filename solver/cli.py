"""``solve``: one forward sample from the command line."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import click
from click.core import ParameterSource

from elastimap.cli_util import CONTEXT_SETTINGS, Choice, geometry_option, mesh_option, param_flags, run, sizing_option
from elastimap.errors import UserError
from elastimap.sensor import Sensor

from .params import INTERFACES, THICKNESS, Discretisation, ImageSpec, Inclusion, Probe, from_sensor


def _layers(text: str | None):
    if text is None:
        return Probe().layers
    try:
        out = tuple(tuple(float(v) for v in part.split(":")) for part in text.split(","))
    except ValueError:
        out = ()
    if not out or any(len(l) != 2 for l in out):
        raise UserError("--layers", f"expected THICK:E,THICK:E,... in mm:kPa from the tissue side (got {text!r})")
    return out


def sensor_with_flags(path: str | None, flags: dict, given) -> Sensor:
    """The description of ``--sensor`` (the paper's without it) with the sensor flags applied.

    With ``--sensor``, only the flags given on the command line (``given(name)``) override the
    file; without it every flag applies, as it always did.  ``flags`` holds the values of
    ``layers``, ``nu``, ``tissue_E``, ``thickness``, ``delta``, ``force`` and ``interface``.
    """
    from elastimap.sensor import Layer, load

    s = load(path) if path else Sensor()
    use = (lambda k: given(k) and k in flags) if path else (lambda k: k in flags)
    probe, tissue, loading, itf = s.probe, s.tissue, s.loading, s.interface
    if use("layers"):
        probe = replace(probe, layers=tuple(Layer(t, E) for t, E in _layers(flags["layers"])))
    if use("nu"):
        probe, tissue = replace(probe, nu=flags["nu"]), replace(tissue, nu=flags["nu"])
    if use("tissue_E"):
        tissue = replace(tissue, E=flags["tissue_E"])
    if use("thickness"):
        tissue = replace(tissue, thickness=flags["thickness"])
    if use("delta"):
        loading = replace(loading, delta=flags["delta"])
    if use("force"):
        loading = replace(loading, force=flags["force"])
    if use("interface"):
        itf = replace(itf, model=flags["interface"])
    s = s.replace(probe=probe, tissue=tissue, loading=loading, interface=itf)
    if path:  # the file's fields are checked by name before the solver's own checks
        try:
            s.validate()
        except UserError as exc:
            with_flags = " (with the flags given)" if any(given(k) for k in flags) else ""
            raise UserError("sensor", f"{path}{with_flags}: {exc.param}: {exc.message}") from None
    return s


def sensor_option(help: str = "Sensor description (TOML; docs/howto/your-own-sensor.md) [default: the paper's]."):
    return click.option("--sensor", "sensor_path", type=click.Path(dir_okay=False), default=None, help=help)


def _check_outputs(image_png: str | None, image_npy: str | None, vtx: str | None, sensor_path: str | None) -> None:
    """Every output location is checked before the solve starts."""
    from elastimap.errors import UserError

    keep = {"--sensor": sensor_path}

    for flag, given in (("--image", image_png), ("--image-npy", image_npy), ("--vtx", vtx)):
        if given is not None and not str(given).strip():
            raise UserError(flag, "must be a path (got '')")
    if not (image_png or image_npy or vtx):
        return  # nothing to write: `elastimap.outputs` not imported (0.005 s; docs/forward-model.md, 'Speed')
    from elastimap.outputs import check_out_dir, check_out_file, figure_suffixes

    if image_png:
        check_out_file(image_png, "--image", suffixes=figure_suffixes(), inputs=keep)
    if image_npy:
        if not str(image_npy).endswith(".npy"):
            raise UserError("--image-npy", f"{image_npy}: the file name must end in .npy")
        check_out_file(image_npy, "--image-npy", inputs=keep)
    if vtx:
        # ADIOS2 writes a folder; onto an existing file it aborts the whole process
        check_out_dir(vtx, "--vtx", allow_existing=True)


@param_flags({"probe.layer*": "--layers"})
@click.command(context_settings=CONTEXT_SETTINGS)
@sensor_option(
    "Sensor description (TOML; docs/howto/your-own-sensor.md) [default: the paper's]; the sensor flags "
    "given (--layers, --nu, --tissue-E, --thickness, --delta, --force, --interface) override its fields."
)
@click.option("--d", "d", type=float, default=8.0, show_default=True, help="Inclusion diameter (mm).")
@click.option(
    "--h",
    "h",
    type=float,
    default=7.0,
    show_default=True,
    help="Depth of the inclusion centre below the tissue surface (mm); the sphere must stay >= 1 mm "
    "below the surface and >= 2 mm above the chest wall.",
)
@click.option("--E", "E", type=float, default=50.0, show_default=True, help="Inclusion Young's modulus (kPa).")
@mesh_option()
@click.option(
    "--interface",
    type=Choice(INTERFACES),
    default="tied",
    show_default=True,
    help="Probe-tissue interface: tied = frictionless closed (normal tied, tangentially free); "
    "contact = frictionless unilateral contact (active set); bonded = glued (comparison only).",
)
@geometry_option()
@sizing_option()
@click.option("--full", is_flag=True, help="Full model instead of the quarter-symmetry model.")
@click.option("--delta", type=float, default=3.0, show_default=True, help="Plate indentation (mm).")
@click.option("--force", type=float, default=None, help="Prescribe the total plate force (mN) instead of --delta.")
@click.option("--tissue-E", "tissue_E", type=float, default=5.0, show_default=True, help="Tissue modulus (kPa).")
@click.option("--thickness", type=float, default=THICKNESS, show_default=True, help="Tissue thickness (mm).")
@click.option("--nu", type=float, default=0.49, show_default=True, help="Poisson ratio of tissue, inclusion and probe.")
@click.option(
    "--layers", default=None, help="Probe layers THICK:E,... (mm:kPa) from the tissue side [default: 2:300,3:150,5:50]."
)
@click.option("--pixel", type=float, default=0.5, show_default=True, help="Image pixel size (mm).")
@click.option(
    "--threshold", type=float, default=1e-3, show_default=True, help="O3 threshold on the difference image (mm)."
)
@click.option(
    "--degree", type=click.IntRange(1, 2), default=2, show_default=True, help="Lagrange degree (P1 locks at nu=0.49)."
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (features, force, ndofs, seconds, ...).")
@click.option(
    "--image",
    "image_png",
    type=click.Path(dir_okay=False, writable=True),
    default=None,
    help="Write a PNG of the difference elasticity image (and the raw deflection) with colour bars.",
)
@click.option(
    "--image-npy",
    type=click.Path(dir_okay=False, writable=True),
    default=None,
    help="Write the difference image as a .npy array (mm).",
)
@click.option(
    "--vtx",
    type=click.Path(file_okay=True, dir_okay=True),
    default=None,
    help="Write the displacement field of the inclusion solve for ParaView (ADIOS2 .bp folder).",
)
def cli(
    sensor_path,
    d,
    h,
    E,
    mesh,
    interface,
    geometry,
    sizing,
    full,
    delta,
    force,
    tissue_E,
    thickness,
    nu,
    layers,
    pixel,
    threshold,
    degree,
    as_json,
    image_png,
    image_npy,
    vtx,
):
    """Simulate the sensor pressing tissue that holds a stiff spherical inclusion.

    Runs the inclusion solve and a reference solve (inclusion modulus set to the
    tissue's) on the same mesh and reports the paper's features of the difference
    elasticity image: O1 maximum (mm), O2 total (mm), O3 deformed area (mm^2), plus
    the plate force (mN).  Units: mm, kPa, mN.

    Example: elastimap solve --d 8 --h 7 --E 50 --json --image inclusion.png
    """
    flags = dict(layers=layers, nu=nu, tissue_E=tissue_E, thickness=thickness, delta=delta, force=force)
    disc = Discretisation(
        mesh=mesh, degree=degree, symmetry="full" if full else "quarter", geometry=geometry, sizing=sizing
    )
    sensor, p = _solve_params(sensor_path, flags, interface, Inclusion(d=d, h=h, E=E), disc, pixel, threshold)
    _check_outputs(image_png, image_npy, vtx, sensor_path)  # before the solve, not after it
    res = _run_solve(p, vtx)
    if res is None:
        return 1
    _write_images(res, image_npy, image_png, f"difference image d={d:g} mm h={h:g} mm E={E:g} kPa")
    if as_json:
        from elastimap.provenance import stamp

        click.echo(json.dumps({**res.summary(), **sensor.record(), **stamp()}))
    else:
        _print_summary(res, p, sensor, sensor_path, f"d = {d:g} mm, h = {h:g} mm, E = {E:g} kPa", mesh)
    return 0


def _solve_params(sensor_path, flags: dict, interface: str, lesion: Inclusion, disc, pixel: float, threshold: float):
    """(sensor, validated parameters) of ``solve``: the ``--sensor`` description with the sensor
    ``flags`` and ``--interface`` given applied (:func:`sensor_with_flags`), the lesion ``(d, h, E)``
    with the ``--nu`` given (else the file's tissue ν), the discretisation and the image grid
    (``pixel`` and ``threshold`` mm)."""
    ctx = click.get_current_context()
    given = lambda name: ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)
    sensor = sensor_with_flags(sensor_path, {**flags, "interface": interface}, given)
    lesion_nu = flags["nu"] if (given("nu") or not sensor_path) else sensor.tissue.nu
    p = from_sensor(sensor, replace(lesion, nu=lesion_nu), disc, ImageSpec(pixel=pixel, threshold=threshold)).validate()
    return sensor, p


def _run_solve(p, vtx):
    """The solve of ``p`` (with its displacement field written to ``vtx`` when given); a failed
    solve is a result to report, not a bug: one line on stderr and None (the command exits 1)."""
    from .api import solve
    from .errors import SolverError

    try:
        if vtx:
            from .api import solve_with_fields

            return solve_with_fields(p, vtx)
        return solve(p)
    except SolverError as exc:
        click.echo(f"error: {exc}", err=True)
        return None


def _write_images(res, image_npy, image_png, title: str) -> None:
    """``--image-npy`` (the difference image, mm) and ``--image`` (its PNG with the raw
    deflection, titled ``title`` and the features)."""
    if image_npy or image_png:
        from elastimap.outputs import write_or_fallback
    if image_npy:  # the array first: if the PNG then fails, the numbers are already safe
        import numpy as np

        write_or_fallback(lambda f: np.save(f, res.image), image_npy, "--image-npy")
    if image_png:
        from .plot import save_image_png

        title = f"{title}\nO1={res.O1:.4g} mm O2={res.O2:.4g} mm O3={res.O3:.4g} mm²"
        write_or_fallback(
            lambda f: save_image_png(f, res.image, res.pixel, title, raw=res.image_raw), image_png, "--image"
        )


def _print_summary(res, p, sensor, sensor_path, lesion: str, mesh: str) -> None:
    """``solve``'s report: the sensor (with --sensor), the lesion, the ``--mesh`` level, the
    interface and the symmetry solved (``--full``, or a tilted ``--sensor`` that needs the full
    model), the features O1 (mm), O2 (mm), O3 (mm²), the plate force
    (mN), the interface check and the timings (s)."""
    s = res.summary()
    if sensor_path:
        click.echo(f"sensor {sensor.name!r} ({sensor_path}, hash {sensor.hash()})")
    click.echo(f"{lesion}  ({mesh} mesh, {p.disc.interface} interface, {p.disc.symmetry} model, {res.ndofs} dofs)")
    click.echo(f"O1 = {res.O1:.6g} mm   O2 = {res.O2:.6g} mm   O3 = {res.O3:.6g} mm^2")
    click.echo(f"plate force = {res.force:.6g} mN (reference {res.force_ref:.6g} mN) at delta = {res.delta:.6g} mm")
    click.echo(
        f"interface: min patch tension fraction {s['interface_check']['tension_patch_fraction']:.3g}, "
        f"open pairs {s['interface_check']['open_pair_fraction']:.3g}"
    )
    click.echo(
        f"{res.seconds:.2f} s, peak memory {res.peak_memory_mb:.0f} MiB; "
        + ", ".join(f"{k} {v:.2f}s" for k, v in res.timings.items())
    )


def main(argv: list[str] | None = None) -> None:
    run(cli, argv, prog_name="solve")


if __name__ == "__main__":
    main(sys.argv[1:])
