"""The command line as a whole: one `elastimap` command, its aliases, -h everywhere, fast errors.

Most checks use click's CliRunner on the very objects the console scripts run; a few run
the installed scripts in ``.venv/bin`` as a user would, and time them.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from elastimap.cli import STAGES, cli
from elastimap.cli_util import flag_for, load_command, param_flags, run
from elastimap.constraints import InstanceOf, Interval, Options, Predicate, validate_params
from elastimap.errors import UserError
from elastimap.workflows.studies import command_specs

STUDIES = command_specs()

BIN = Path(sys.executable).parent
ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}

# alias (console script) -> the `elastimap` path that runs the same click object
ALIASES = {
    "solve": ["solve"],
    "sweep": ["sweep"],
    "dataset": ["dataset"],
    "train": ["train"],
    "camera": ["camera"],
    "calibrate": ["camera", "calibrate"],
    "infer": ["camera", "infer"],
    "gap": ["gap"],
}


def _resolve(path: list[str]) -> click.Command:
    cmd: click.Command = cli
    ctx = click.Context(cli)
    for name in path:
        assert isinstance(cmd, click.Group), path
        cmd = cmd.get_command(ctx, name)
        assert cmd is not None, f"elastimap {' '.join(path)}: no such command"
    return cmd


def _walk(cmd: click.Command, path: list[str]):
    yield path, cmd
    if isinstance(cmd, click.Group):
        ctx = click.Context(cmd)
        for name in cmd.list_commands(ctx):
            yield from _walk(cmd.get_command(ctx, name), path + [name])


def _script_entry_points() -> dict[str, md.EntryPoint]:
    return {ep.name: ep for ep in md.distribution("elastimap").entry_points if ep.group == "console_scripts"}


# ----------------------------------------------------------------------------- the one command
def test_help_lists_every_stage():
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0, r.output
    for name in [*STAGES, "study", "demo"]:
        assert f"\n  {name} " in r.output, name
    r = CliRunner().invoke(cli, ["study", "-h"])
    assert r.exit_code == 0 and all(f"\n  {s} " in r.output for s in STUDIES)


def test_every_lazy_entry_resolves_to_a_click_command():
    for table in (STAGES, STUDIES):
        for spec, help_line in table.values():
            assert isinstance(load_command(spec), click.Command), spec
            assert help_line and "\n" not in help_line


def test_console_scripts_are_the_documented_set():
    eps = _script_entry_points()
    assert set(eps) == {"elastimap", *ALIASES}
    assert eps["elastimap"].value == "elastimap.cli:main"


@pytest.mark.parametrize("alias", sorted(ALIASES))
def test_alias_runs_the_same_click_object_as_elastimap(alias, monkeypatch):
    """Each console script hands `run` the very object `elastimap <path>` resolves to."""
    ep = _script_entry_points()[alias]
    fn = ep.load()
    seen = []
    mod = sys.modules[fn.__module__]
    for name in ("run", "run_cli"):
        if getattr(mod, name, None) is run:
            monkeypatch.setattr(mod, name, lambda command, *a, **k: seen.append(command))
    fn()
    assert seen and seen[0] is _resolve(ALIASES[alias])


def test_dash_h_on_every_group_and_subcommand():
    """Walk the whole click tree (stages, their subcommands, the studies): `-h` shows the usage."""
    n = 0
    for path, _cmd in _walk(cli, []):
        r = CliRunner().invoke(cli, [*path, "-h"])
        assert r.exit_code == 0 and "Usage:" in r.output and "--help" in r.output, (path, r.output)
        n += 1
    assert n >= 1 + len(STAGES) + len(STUDIES) + 2
    # and on each alias object on its own (as its console script runs it)
    for alias, path in ALIASES.items():
        obj = _resolve(path)
        for sub, _ in _walk(obj, []):
            r = CliRunner().invoke(obj, [*sub, "-h"], prog_name=alias)
            assert r.exit_code == 0 and f"Usage: {alias}" in r.output, (alias, sub, r.output)


def test_mesh_is_one_checked_choice_everywhere():
    from elastimap.solver.params import MESH_LEVELS

    found = 0
    for path, cmd in _walk(cli, []):
        for p in cmd.params:
            if p.name == "mesh":
                found += 1
                assert isinstance(p.type, click.Choice) and tuple(p.type.choices) == MESH_LEVELS, path
    assert found >= 8


# ----------------------------------------------------------------------------- errors name flags
def test_flag_for_maps_python_names_to_flags():
    @param_flags({"probe.layer*": "--layers"})
    @click.command()
    @click.argument("path")
    @click.option("--jobs", type=int)
    @click.option("--batch-rows", type=int)
    @click.option("--tissue-E", "tissue_E", type=float)
    @click.option("--nu", type=float)
    @click.option("--sensor", "sensor_json")
    @click.option("--camera-csv")
    def cmd(**kw):
        pass

    for name, flag in [
        ("jobs", "--jobs"),
        ("batch_rows", "--batch-rows"),
        ("tissue.E", "--tissue-E"),
        ("inclusion.nu", "--nu"),
        ("probe.layer2.E", "--layers"),
        ("sensor", "--sensor"),
        ("camera-csv", "--camera-csv"),
        ("path", "PATH"),
        ("--already", "--already"),
        ("unknown_thing", "unknown_thing"),
    ]:
        assert flag_for(cmd, name) == flag, name


def test_library_names_become_flags_in_one_line(capsys):
    """SweepConfig says `jobs`; the command line says `--jobs`, one line, exit 2."""
    from elastimap.sweep.run import SweepConfig, make_plan

    with pytest.raises(UserError) as e:
        make_plan(SweepConfig(jobs=0, mesh="tiny"))
    assert e.value.param == "jobs"
    for argv, flag in [
        (["sweep", "run", "--jobs", "0"], "--jobs"),
        (["sweep", "run", "--batch-rows", "0"], "--batch-rows"),
        (["sweep", "run", "--ranges", "d=5:2"], "--ranges"),
        (["solve", "--tissue-E", "-1"], "--tissue-E"),
        (["solve", "--layers", "2:0"], "--layers"),
        (["train", "--synthetic", "60", "--feature-noise", "2"], "--feature-noise"),
        (["train", "--synthetic", "60", "--repeats", "0"], "--repeats"),
    ]:
        with pytest.raises(SystemExit) as ex:
            run(cli, argv, prog_name="elastimap")
        err = capsys.readouterr().err
        assert ex.value.code == 2 and err.startswith(f"error: {flag}: ") and err.count("\n") == 1, (argv, err)


# ----------------------------------------------------------------------------- declared rules
def test_constraints_validate_and_describe():
    table = {
        "jobs": [Interval(int, 1, 256)],
        "timeout": [None, Interval(float, 0, None, unit="s")],
        "design": [Options(("lhs", "sobol"))],
        "device": [None, InstanceOf(bytes, "bytes"), Predicate(lambda d: d.startswith("cuda"), "cuda[:N]")],
    }
    validate_params({"jobs": 2, "timeout": None, "design": "lhs", "device": "cuda:1"}, table)
    for values, msg in [
        ({"jobs": 0}, "jobs: must be an integer in [1, 256] (got 0)"),
        ({"jobs": 2.0}, "jobs: must be an integer in [1, 256] (got 2)"),
        ({"jobs": True}, "jobs: must be an integer"),
        ({"timeout": -1.0}, "timeout: must be >= 0 s (got -1)"),
        ({"timeout": float("nan")}, "timeout: must be >= 0 s"),
        ({"design": "grid"}, "design: must be one of lhs, sobol (got 'grid')"),
        ({"device": "tpu"}, "device: must be bytes or cuda[:N] (got 'tpu')"),
    ]:
        with pytest.raises(UserError) as e:
            validate_params(values, table)
        assert str(e.value).startswith(msg), (values, str(e.value))
    assert str(Interval(float, 0, 1, closed="left")) == "in [0, 1)"
    assert str(Interval(float, 0, None, closed="neither", unit="kPa")) == "> 0 kPa"


def test_sweep_config_takes_a_dict_of_ranges(tmp_path):
    from elastimap.sweep.run import SweepConfig, make_plan

    plan = make_plan(SweepConfig(n=4, mesh="tiny", ranges={"d": (3, 9), "E": (20, 40, "log")}, out=str(tmp_path / "o")))
    assert (plan.ranges["d"].lo, plan.ranges["d"].hi) == (3.0, 9.0) and plan.ranges["E"].scale == "log"
    assert plan.ranges["h"].auto and all(3 <= s["d"] <= 9 for s in plan.samples)
    with pytest.raises(UserError) as e:
        make_plan(SweepConfig(n=4, mesh="tiny", ranges="d=3:9"))
    assert e.value.param == "ranges"


def test_train_config_declares_its_rules():
    pytest.importorskip("torch")
    from elastimap.training.experiment import TrainConfig

    TrainConfig().validate()
    for kw, name in [
        (dict(epochs=-1), "epochs"),
        (dict(val_fraction=1.0), "val_fraction"),
        (dict(workers=-1), "workers"),
        (dict(device="gpu"), "device"),
        (dict(hidden=((0, "tansig"),)), "hidden"),
    ]:
        with pytest.raises(UserError) as e:
            TrainConfig(**kw).validate()
        assert e.value.param == name


# ----------------------------------------------------------------------------- installed scripts, timed
def _timed(argv):
    """Run ``argv``; return the result, its wall time and the CPU time (user + sys) it used."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=120)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r, wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


@pytest.mark.parametrize(
    "argv",
    [
        ["elastimap", "solve", "--bogus"],
        ["solve", "--bogus"],
        ["elastimap", "sweep", "run", "--bogus"],
        ["sweep", "run", "--bogus"],
        ["elastimap", "train", "--bogus"],
        ["train", "--bogus"],
        ["elastimap", "camera", "infer", "--bogus"],
        ["infer", "--bogus"],
        ["elastimap", "study", "crbmap", "--bogus"],
        ["elastimap", "--bogus"],
    ],
)
def test_mistyped_flag_answers_fast_in_one_line(argv):
    exe = BIN / argv[0]
    if not exe.exists():
        pytest.skip(f"{exe} not installed")
    r, wall, cpu = _timed([str(exe), *argv[1:]])
    print(f"{' '.join(argv)}: exit {r.returncode} in {wall:.2f} s wall, {cpu:.2f} s CPU")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    assert "--bogus" in r.stderr and "Traceback" not in r.stderr
    # The goal is well under 1 s.  What the command itself costs is its CPU time (about 0.1-0.4 s
    # measured; importing torch alone took 6-12 s); the wall time also holds the wait for a core,
    # which on the shared 2-core test machine can be seconds, so its bound is generous.
    assert cpu < 1.0, f"{' '.join(argv)} used {cpu:.2f} s CPU"
    assert wall < 5.0, f"{' '.join(argv)} took {wall:.2f} s"


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["solve", "--bogus"],
        ["sweep", "run", "--bogus"],
        ["train", "--bogus"],
        ["camera", "-h"],
        ["gap", "-h"],
        ["study", "-h"],
    ],
)
def test_lazy_imports_nothing_heavy(argv):
    code = (
        f"import sys\nfrom elastimap.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
        "heavy = sorted(m for m in ('torch', 'dolfinx', 'dask', 'distributed', 'pandas', 'gmsh') if m in sys.modules)\n"
        "print('HEAVY', ','.join(heavy))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("HEAVY")]
    assert line == ["HEAVY "], (argv, r.stdout[-500:], r.stderr[-500:])


def test_help_of_top_command_does_not_even_import_numpy():
    code = (
        "import sys\nfrom elastimap.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print('NUMPY', 'numpy' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert "NUMPY False" in r.stdout, r.stdout[-300:]


def test_scripts_and_elastimap_give_the_same_answers(tmp_path):
    """Real runs of installed scripts: the alias and `elastimap X` print the same."""
    for alias, sub in [
        ("gap", ["effects"]),
        ("camera", ["-h"]),
        ("infer", ["-h"]),
        ("calibrate", ["-h"]),
        ("sweep", ["run", "-h"]),
        ("dataset", ["inspect", "-h"]),
        ("solve", ["-h"]),
        ("train", ["-h"]),
    ]:
        exe = BIN / alias
        if not exe.exists():
            pytest.skip(f"{exe} not installed")
        a = subprocess.run([str(exe), *sub], capture_output=True, text=True, env=ENV, timeout=120)
        b = subprocess.run(
            [str(BIN / "elastimap"), *ALIASES[alias], *sub], capture_output=True, text=True, env=ENV, timeout=120
        )
        assert a.returncode == b.returncode == 0, (alias, a.stderr, b.stderr)
        if sub == ["-h"] or sub[-1] == "-h":  # same help but for the program name in the usage line
            assert a.stdout.startswith(f"Usage: {alias} {' '.join(sub[:-1])}".rstrip())
            assert b.stdout.startswith(f"Usage: elastimap {' '.join(ALIASES[alias] + sub[:-1])}".rstrip())
            assert a.stdout.split("\n", 2)[2] == b.stdout.split("\n", 2)[2], alias
        else:
            assert a.stdout == b.stdout and a.stdout, alias


def test_python_dash_m_entries_still_work():
    for mod in (
        "elastimap.cli",
        "elastimap.solver.cli",
        "elastimap.sweep.cli",
        "elastimap.dataset.cli",
        "elastimap.gap.cli",
        "elastimap.camera.cli",
    ):
        r = subprocess.run([sys.executable, "-m", mod, "-h"], capture_output=True, text=True, env=ENV, timeout=120)
        assert r.returncode == 0 and "Usage:" in r.stdout, (mod, r.stderr[-300:])


def test_train_runs_as_elastimap_train_and_as_train(tmp_path):
    """One real (tiny, SYNTHETIC toy table) training through both spellings gives the same table."""
    pytest.importorskip("torch")
    args = [
        "--synthetic",
        "40",
        "--algo",
        "scg",
        "--validate",
        "hov",
        "--repeats",
        "1",
        "--epochs",
        "3",
        "--hidden",
        "3",
        "--no-model",
        "--no-progress",
        "--threads",
        "1",
        "--workers",
        "1",
    ]
    train_obj = _resolve(["train"])
    r1 = CliRunner().invoke(cli, ["train", *args, "--out", str(tmp_path / "a")])
    r2 = CliRunner().invoke(train_obj, [*args, "--out", str(tmp_path / "b")])
    assert r1.exit_code == 0 and r2.exit_code == 0, (r1.output[-500:], r2.output[-500:])
    ja = json.loads((tmp_path / "a" / "run.json").read_text())
    jb = json.loads((tmp_path / "b" / "run.json").read_text())
    assert ja["data_sha256"] == jb["data_sha256"]
    import pandas as pd

    a, b = pd.read_csv(tmp_path / "a" / "results.csv"), pd.read_csv(tmp_path / "b" / "results.csv")
    metrics = [c for c in a.columns if c.startswith(("mse100", "mre", "rmse"))]
    assert metrics and a[metrics].equals(b[metrics])


def test_shard_option_parses_k_of_n_and_rejects_the_rest():
    from elastimap.cli_util import run, shard_option

    @click.command()
    @shard_option()
    def cmd(shard):
        click.echo(f"{shard[0]} of {shard[1]}")

    assert CliRunner().invoke(cmd, ["--shard", "1/3"]).output == "1 of 3\n"
    assert CliRunner().invoke(cmd, []).output == "0 of 1\n"
    for bad in ("3/2", "x", "1/0", "-1/2", "1/2/3"):
        with pytest.raises(SystemExit) as exc:
            run(cmd, ["--shard", bad])
        assert exc.value.code == 2, bad
