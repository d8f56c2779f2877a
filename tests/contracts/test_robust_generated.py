"""Bad inputs generated from the declared rules, so that a new option is covered without a new case.

In the style of scikit-learn's ``generate_invalid_param_val`` (``sklearn/utils/_param_validation``):
for every rule table the package declares (``_parameter_constraints``, found by reading the
source, see :mod:`elastimap.constraints`) values that break a rule are made from the rule itself
(just below / above each bound, the wrong type, NaN, ±inf, a 20-digit integer, a string not
among the options) and, with hypothesis, drawn at random from everything a user could type; each
must be refused with the parameter named.  The tables that belong to a command are then driven
through that command's flags (in-process, the flag found with :func:`elastimap.cli_util.flag_for`):
exit code 2, one line naming the flag, nothing written.  Finally every ``float`` and ``int`` option
of every command (walked from the ``elastimap`` group) is given ``nan``, ``inf`` and a 20-digit
integer.
"""

from __future__ import annotations

import importlib
import math
import re
from pathlib import Path

import click
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_bad_inputs import assert_refused, invoke, snapshot

from elastimap.cli_util import flag_for
from elastimap.constraints import InstanceOf, Interval, Options, Predicate, validate_params
from elastimap.errors import UserError

pytestmark = pytest.mark.xdist_group("test_robust_generated")

REPO = Path(__file__).resolve().parents[2]
ROOMS = ("elastimap", "solver", "sweep", "dataset", "training", "identify", "camera", "gap")
HUGE = 10**20


# ----------------------------------------------------------------------------- the tables
def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = rel.parts
    return ".".join(parts) if parts[0] == "elastimap" else "elastimap." + ".".join(parts)


def declared_tables() -> dict[str, dict]:
    """``{"module.Owner": table}`` for every ``_parameter_constraints`` the rooms declare."""
    found = {}
    for room in ROOMS:
        for path in sorted((REPO / room).rglob("*.py")):
            if "_parameter_constraints = {" not in path.read_text():
                continue
            mod = importlib.import_module(_module_name(path))
            if isinstance(getattr(mod, "_parameter_constraints", None), dict):
                found[mod.__name__] = mod._parameter_constraints
            for name, obj in vars(mod).items():
                table = getattr(obj, "_parameter_constraints", None) if isinstance(obj, type) else None
                if isinstance(table, dict) and obj.__module__ == mod.__name__:
                    found[f"{mod.__name__}.{name}"] = table
    return found


TABLES = declared_tables()


def _satisfied(rules: list, v) -> bool:
    if v is None and None in rules:
        return True
    for r in rules:
        try:
            if r is not None and r.is_satisfied_by(v):
                return True
        except Exception:  # a rule that cannot judge the value: validate_params must still refuse it
            pass
    return False


def generate_invalid_param_val(rule) -> list:
    """Values that break ``rule`` (sklearn's idea): past each bound, the wrong kind, non-finite."""
    out: list = ["not-a-value", [1], {"a": 1}, object()]
    if isinstance(rule, Interval):
        step = 1 if rule.kind is int else 1e-9 * max(1.0, abs(rule.lo or 0), abs(rule.hi or 0))
        if rule.lo is not None:
            out += [rule.lo - step, rule.lo - 1, -HUGE]
            if rule.closed in ("right", "neither"):
                out.append(rule.lo)
        if rule.hi is not None:
            out += [rule.hi + step, rule.hi + 1, HUGE]
            if rule.closed in ("left", "neither"):
                out.append(rule.hi)
        out += [math.nan, math.inf, -math.inf, True]
        if rule.kind is int:
            out += [1.5, "3"]
    elif isinstance(rule, Options):
        out += ["no-such-option", 12345]
    elif isinstance(rule, (InstanceOf, Predicate)):
        out += [-1, 0, math.nan, ""]
    return out


CASES = [
    (owner, name, v)
    for owner, table in TABLES.items()
    for name, rules in table.items()
    for rule in rules
    if rule is not None
    for v in generate_invalid_param_val(rule)
    if not _satisfied(rules, v)
]


def test_the_tables_are_found():
    names = set(TABLES)
    assert {"elastimap.sweep.run.SweepConfig", "elastimap.training.experiment.TrainConfig"} <= names, names
    assert len(CASES) > 100


@pytest.mark.parametrize(
    ("owner", "name", "value"), CASES, ids=[f"{o.rsplit('.', 1)[-1]}-{n}-{i}" for i, (o, n, _) in enumerate(CASES)]
)
def test_generated_invalid_value_is_refused_naming_it(owner, name, value):
    with pytest.raises(UserError) as ei:
        validate_params({name: value}, TABLES[owner])
    assert ei.value.param == name
    assert "must be" in ei.value.message and "\n" not in str(ei.value)


TYPED = st.one_of(
    st.integers(-(10**25), 10**25),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.none(),
    st.booleans(),
)


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_anything_a_rule_does_not_allow_is_refused(data):
    owner = data.draw(st.sampled_from(sorted(TABLES)))
    name = data.draw(st.sampled_from(sorted(TABLES[owner])))
    rules = TABLES[owner][name]
    v = data.draw(TYPED.filter(lambda x: not _satisfied(rules, x)))
    with pytest.raises(UserError) as ei:
        validate_params({name: v}, TABLES[owner])
    assert ei.value.param == name and "\n" not in str(ei.value)


# ----------------------------------------------------------------------------- through the commands
#: A table that belongs to a command, and arguments that make that command quick and harmless
#: (the SYNTHETIC solver, the toy backend, tiny nets) in case a bad value were let through.
COMMANDS = {
    "elastimap.sweep.run.SweepConfig": (
        "sweep",
        ["run", "--solver", "synthetic", "--mesh", "tiny", "--n", "1", "--jobs", "1", "--no-progress", "--out", "o"],
    ),
    "elastimap.training.experiment.TrainConfig": (
        "train",
        ["--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress", "--out", "o"],
    ),
    "elastimap.gap.synth": (
        "gap",
        ["synth", "--backend", "toy", "--cache", "none", "--n", "4", "--frames", "2", "--mesh", "tiny", "--no-progress"]
        + ["--out", "o"],
    ),
}


def _command(script: str, args: list[str]) -> click.Command:
    """The leaf command ``script args`` runs, found from the ``elastimap`` group (same objects)."""
    from elastimap.cli import cli
    from elastimap.cli_util import _leaf_command

    return _leaf_command(cli, [script, *args], "elastimap")


def _as_text(v) -> str | None:
    if isinstance(v, bool) or v is None or isinstance(v, (list, dict)) or type(v) is object:
        return None
    return repr(v) if isinstance(v, float) else str(v)


def _flag_cases():
    cases = []
    for owner, (script, base) in COMMANDS.items():
        cmd = _command(script, base)
        by_flag = {o: p for p in cmd.params for o in getattr(p, "opts", [])}
        for o, name, v in CASES:
            text = _as_text(v)
            flag = flag_for(cmd, name)
            if o != owner or text is None or flag not in by_flag:
                continue
            try:  # what the command hands the library: a typed value can be valid again ("3")
                typed = by_flag[flag].type.convert(text, by_flag[flag], None)
            except click.BadParameter:
                typed = v  # refused by the option's type already
            if not _satisfied(TABLES[owner][name], typed) and not (typed == "" and None in TABLES[owner][name]):
                cases.append((script, tuple(base), flag, text))
    return sorted(set(cases))


FLAG_CASES = _flag_cases()


def test_every_command_table_reaches_its_flags():
    flags = {(s, f) for s, _, f, _ in FLAG_CASES}
    assert ("sweep", "--jobs") in flags and ("train", "--epochs") in flags and ("gap", "--seed") in flags, flags


@pytest.mark.parametrize(
    ("script", "base", "flag", "text"), FLAG_CASES, ids=[f"{s}{f}={t}" for s, _, f, t in FLAG_CASES]
)
def test_generated_invalid_flag_value_is_refused(script, base, flag, text, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = invoke(script, [*base, flag, text])
    assert_refused(code, out, err, (flag,))
    assert snapshot(tmp_path) == {}


# ----------------------------------------------------------------------------- every number option
def _leaves(cmd: click.Command, path: tuple[str, ...] = ()):
    if isinstance(cmd, click.Group):
        ctx = click.Context(cmd)
        for name in cmd.list_commands(ctx):
            sub = cmd.get_command(ctx, name)
            if sub is not None:
                yield from _leaves(sub, (*path, name))
    else:
        yield path, cmd


def _number_cases():
    from elastimap.cli import cli

    cases = []
    for path, cmd in _leaves(cli):
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.is_flag:
                continue
            t = p.type.types[0] if isinstance(p.type, click.Tuple) else p.type
            flag = max(p.opts, key=len)
            n = p.nargs if p.nargs > 0 else 1
            if isinstance(t, click.types.FloatParamType) and not isinstance(t, click.FloatRange):
                cases += [(path, flag, [v] * n) for v in ("nan", "inf", "-inf")]
            elif isinstance(t, click.types.IntParamType) and not isinstance(t, click.IntRange):
                cases += [(path, flag, [v] * n) for v in (str(HUGE), str(-HUGE))]
    return cases


NUMBER_CASES = _number_cases()


@pytest.mark.parametrize(("path", "flag", "values"), NUMBER_CASES, ids=lambda x: re.sub(r"\W+", "-", str(x))[:40])
def test_non_finite_and_huge_numbers_refused_on_every_command(path, flag, values, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = invoke("elastimap", [*path, flag, *values])
    assert_refused(code, out, err, (flag,))
    assert snapshot(tmp_path) == {}


def test_every_command_was_walked():
    walked = {p for p, _, _ in NUMBER_CASES}
    assert {("solve",), ("sweep", "run"), ("train",), ("gap", "synth"), ("camera", "infer")} <= walked, walked
    assert len(NUMBER_CASES) > 100
