"""The README's examples are valid input and run, its commands are the ones CI runs, and every ``rigsfm`` command
line of the README and docs/ names a verb and options that exist."""

import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from rigsfm.core.rig import parse_camera, parse_rigid3d

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def yaml_blocks():
    return [yaml.safe_load(block) for block in re.findall(r"```yaml\n(.*?)```", README, re.S)]


def test_rigs_yaml_example_is_valid():
    rigs_example = next(block for block in yaml_blocks() if "rigs" in block)
    for rig in rigs_example["rigs"]:
        for sensor in ("wide", "narrow"):
            parse_camera(rig["sensors"][sensor], f"README {sensor}")
        parse_rigid3d(rig["narrow_from_wide"], "README narrow_from_wide")


def test_ci_runs_the_readme_test_command():
    command = ("bash scripts/setup.sh && .venv/bin/python -m ruff check rigsfm tests benchmarks workflows && "
               ".venv/bin/python -m mypy && .venv/bin/python -m pytest -q")
    assert f"```bash\n{command}\n```" in README
    assert command in (ROOT / ".ci" / "run").read_text().splitlines()


def test_bad_inputs_table_is_what_rigsfm_says():
    """README's "When something is wrong" table, row by row, against a fresh run of each case (the cases that
    need a mount namespace are only checked to be there). Refresh with `python tests/bad_inputs_table.py --readme`."""
    from bad_inputs_table import CASES, readme_rows, rows

    written = readme_rows(README)
    assert len(written) >= 30 and [row[0] for row in written] == [case.did for case in CASES]
    fresh = {row[0]: row for row in rows(isolated=False)}
    for row in written:
        if row[0] in fresh:
            assert row == fresh[row[0]], f"README row out of date:\n{row}\nrigsfm now says:\n{fresh[row[0]]}"
    assert len(fresh) == len(written) - sum(bool(case.isolated) for case in CASES)


DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
VERB = re.compile(r"(?:^|`|\.venv/bin/)rigsfm ([a-z]+)\b([^`\n]*)")  # in code: a bash line, `...`


def bash_lines(text: str) -> list[str]:
    """The lines of the ```bash blocks, a synopsis's indented continuation lines joined to their first."""
    lines: list[str] = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.splitlines():
            if line[:1].isspace() and lines:
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.strip())
    return lines


def rigsfm_commands() -> list[tuple[str, str, str, bool]]:
    """Every ``rigsfm VERB ...`` the README and docs/ show: (page, verb, the rest, whether it is a bash line to
    copy as it stands, not a synopsis with [options] and a|b choices)."""
    found = []
    for page in DOCS:
        text = page.read_text()
        runnable = {line for line in bash_lines(text) if not re.search(r"[\[|]|\.\.\.", line)}
        for line in bash_lines(text) + re.findall(r"[^\n]+", text):
            for verb, rest in VERB.findall(line):
                found.append((page.name, verb, rest, line in runnable))
    return list(dict.fromkeys(found))


@pytest.mark.slow  # a run on a rendered scene
def test_readme_python_example_runs(rendered, tmp_path, monkeypatch, capsys):
    """The README's Python block, run as written in a folder whose IMAGES, rigs.yaml and scale.yaml are a
    rendered 3-rig scene: it maps, writes OUT and prints a pair's band."""
    from rigsfm.synth.scene import SceneOptions

    (block,) = re.findall(r"```python\n(.*?)```", README, re.S)
    dataset = rendered(SceneOptions(num_rigs=3, arc_deg=120.0, image_scale=0.5, seed=1))
    for name, source in (("IMAGES", dataset.images), ("rigs.yaml", dataset.rigs), ("scale.yaml", dataset.scale)):
        (tmp_path / name).symlink_to(source)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "Registration(registered=3, total=3) []", printed
    i, j, band = printed[1].split()
    assert (i, j) == ("rig01/narrow/frame0000.png", "rig02/narrow/frame0000.png") and 1.0 < float(band) < 50.0
    a, b, c = namespace["a"], namespace["b"], namespace["c"]
    assert abs(a * 400.0 + b * 300.0 + c) > 0.0 and (a, b) != (0.0, 0.0)
    # Run from here with relative paths, the result is still read from elsewhere with its images (the report's
    # epipolar figures, explore, export --images): summary.json names IMAGES absolutely.
    from rigsfm.inspect import write_report

    images = Path(json.loads((tmp_path / "OUT" / "summary.json").read_text())["inputs"]["images"])
    assert images.is_absolute() and images.samefile(tmp_path / "IMAGES")
    monkeypatch.chdir(tmp_path.parent)
    assert "not found: no epipolar figures" not in write_report(tmp_path / "OUT").read_text()


@pytest.mark.parametrize("page", [page.name for page in DOCS])
def test_every_rigsfm_command_parses(page, monkeypatch):
    """Every ``rigsfm VERB ...`` in the README and docs/ (prose, synopses, the bad-inputs table's messages) names a
    verb and options that exist; a bash line without [options] parses as it stands (from the repository root)."""
    import typer

    from rigsfm.cli import app

    group = typer.main.get_command(app)
    monkeypatch.chdir(ROOT)
    commands = [command for command in rigsfm_commands() if command[0] == page]
    for _, verb, rest, runnable in commands:
        assert verb in group.commands, f"{page}: rigsfm {verb}{rest}: no such command"  # type: ignore[attr-defined]
        command = group.commands[verb]  # type: ignore[attr-defined]
        options = {"--help"} | {name for param in command.params for name in [*param.opts, *param.secondary_opts]
                                if name.startswith("--")}
        for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest):
            assert option in options, f"{page}: rigsfm {verb}{rest}: {verb} has no option {option}"
        if runnable:
            try:
                command.make_context(verb, shlex.split(rest))
            except typer.TyperException as error:
                raise AssertionError(f"{page}: rigsfm {verb}{rest}: {error.format_message()}") from error
    if page == "README.md":
        assert sum(runnable for *_, runnable in commands) >= 5


def anchor(heading: str) -> str:
    """GitHub's id of a Markdown heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_links_between_the_pages_resolve():
    """Every relative link of the README, docs/ and benchmarks/README.md names a file that exists and, with #, one
    of its headings."""
    pages = [*DOCS, ROOT / "benchmarks" / "README.md"]
    checked = 0
    for page in pages:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, fragment = target.partition("#")
            linked = (page.parent / path).resolve() if path else page
            assert linked.exists(), f"{page.name}: link to {target}: no such file"
            if fragment:
                headings = re.findall(r"^#+ (.*)$", re.sub(r"```.*?```", "", linked.read_text(), flags=re.S), re.M)
                assert fragment in {anchor(h) for h in headings}, f"{page.name}: link to {target}: no such heading"
            checked += 1
    assert checked >= 30
