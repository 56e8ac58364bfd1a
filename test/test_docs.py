"""The documents a user reads: links that lead somewhere, scripts that exist, and the README's two commands.

The README links into ``docs/measured-figures.md`` by heading; a renamed heading or a moved script would otherwise
leave a link that silently lands at the top of a 2500-line page, or a command that fails on a fresh clone.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", ROOT / "bags" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")
SCRIPT = re.compile(r"\bscripts/[\w.-]+\.(?:sh|py)\b")


def without_code_blocks(text: str) -> str:
    """The text with its fenced code blocks blanked out (a ``[x](y)`` inside code is not a link)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)


def github_slug(title: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation but ``-`` and ``_`` dropped, spaces to ``-``."""
    text = LINK.sub(r"\1", title).replace("`", "").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file, repeated titles numbered as GitHub numbers them (``-1``, ``-2``)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for line in without_code_blocks(path.read_text()).splitlines():
        match = re.match(r"#{1,6} (.+)$", line)
        if match:
            slug = github_slug(match.group(1))
            count = seen.get(slug, 0)
            seen[slug] = count + 1
            out.add(slug if count == 0 else f"{slug}-{count}")
    return out


def broken_links(path: Path) -> list[str]:
    """The relative links of ``path`` whose file or heading does not exist, each with the reason."""
    problems = []
    for text, target in LINK.findall(without_code_blocks(path.read_text())):
        if re.match(r"[a-z]+://|mailto:", target):
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        label = " ".join(text.split())
        if not linked.exists():
            problems.append(f"[{label}]({target}): no file {linked}")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            problems.append(f"[{label}]({target}): no heading #{anchor} in {linked.name}")
    return problems


def test_github_slug_follows_githubs_rules() -> None:
    """The slugs the link check compares against, for headings with code, punctuation and a percent sign."""
    cases = {
        "Comparing policies: `roigsf bench`": "comparing-policies-roigsf-bench",
        "Finer carved cells: `unseen_voxel_m=0.025`; a floor": "finer-carved-cells-unseen_voxel_m0025-a-floor",
        "Stretched new surfels under the 20 % keyframe set": "stretched-new-surfels-under-the-20--keyframe-set",
    }
    for title, slug in cases.items():
        assert github_slug(title) == slug
    assert github_slug("Issue 10's verdicts") == "issue-10s-verdicts"


def test_the_link_check_finds_a_missing_file_and_a_missing_heading(tmp_path: Path) -> None:
    """Links to a missing file and to missing headings are reported; good ones and links in code are not."""
    (tmp_path / "other.md").write_text("# Other\n\n## A section: `x`\n\n## A section: `x`\n")
    doc = tmp_path / "doc.md"
    doc.write_text(
        "# Doc\n\nSee [a](other.md#a-section-x), [b](other.md#a-section-x-1), [c](#doc), [web](https://example.org).\n"
        "Broken: [gone](missing.md), [no such\nheading](other.md#a-section), [here](#nowhere).\n"
        "```\n[in code](missing-too.md)\n```\n"
    )
    problems = broken_links(doc)
    assert len(problems) == 3, problems
    assert "no file" in problems[0] and "missing.md" in problems[0]
    assert problems[1] == "[no such heading](other.md#a-section): no heading #a-section in other.md"
    assert "#nowhere" in problems[2]


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_leads_to_a_file_and_heading_that_exist(path: Path) -> None:
    """README.md, bags/README.md and docs/*.md: each relative link names an existing file and, with ``#``, a heading."""
    assert broken_links(path) == []


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_script_a_document_names_exists(path: Path) -> None:
    """A ``scripts/...`` command in the documents is one a user can run on a clone of the repository."""
    missing = sorted({name for name in SCRIPT.findall(path.read_text()) if not (ROOT / name).is_file()})
    assert missing == []


def test_readme_first_screen_gives_the_two_commands_and_ci_runs_the_test_one() -> None:
    """The README's first code block is exactly the main job and the tests; .ci/run calls the test command only."""
    readme = (ROOT / "README.md").read_text()
    first_block = re.search(r"^```bash\n(.*?)^```", readme, flags=re.MULTILINE | re.DOTALL)
    assert first_block is not None
    assert readme.index(first_block.group(0)) < len("\n".join(readme.splitlines()[:30]))
    commands = [line.split("#")[0].strip() for line in first_block.group(1).splitlines() if line.strip()]
    assert commands == ["bash scripts/demo.sh", "bash scripts/test.sh"]
    ci_commands = [
        line.strip()
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line.strip() and not line.startswith(("#", "set ", "cd "))
    ]
    assert ci_commands == ["bash scripts/test.sh"]


def documented_roigsf_commands(path: Path) -> list[str]:
    """Every ``roigsf ...`` line of the file's code blocks, continuations joined, usage syntax made concrete.

    ``[--opt X]`` keeps what the brackets hold, ``a|b`` keeps ``a``, ``...`` is dropped and a one-letter placeholder
    becomes 1, so a usage line parses as the command it describes with every option given.
    """
    commands = []
    blocks = re.findall(r"^```(\w*)\n(.*?)^```", path.read_text(), flags=re.MULTILINE | re.DOTALL)
    for block in (text for language, text in blocks if language in ("", "bash")):  # a ```python block pairs too
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #")[0].strip()
            if not line.startswith("roigsf "):
                continue
            line = line.replace("[", "").replace("]", "").replace("...", "")
            line = re.sub(r"(\S+)\|\S+", r"\1", line)
            line = re.sub(r"(?<= )[A-Z](?= |$)", "1", line)  # one-letter placeholders (N, W, H) stand for numbers
            commands.append(" ".join(line.split()))
    return commands


def test_usage_syntax_is_made_concrete(tmp_path: Path) -> None:
    """Optional groups, alternatives and ellipses of a usage line turn into one command that argparse can read."""
    doc = tmp_path / "doc.md"
    doc.write_text(
        "```bash\nroigsf bench --setting stream|pool --seeds N \\\n    [--set NAME=VALUE ...]   # comment\nls\n```\n"
    )
    assert documented_roigsf_commands(doc) == ["roigsf bench --setting stream --seeds 1 --set NAME=VALUE"]
    doc.write_text("```python\nx = 1\n```\n\nText.\n\n```bash\nroigsf map SRC --out RUN\n```\n")
    assert documented_roigsf_commands(doc) == ["roigsf map SRC --out RUN"]  # was []: the fences paired off by one


@pytest.mark.parametrize("path", [ROOT / "README.md", ROOT / "docs" / "measured-figures.md"], ids=lambda p: p.name)
def test_every_documented_roigsf_command_parses(path: Path) -> None:
    """Each ``roigsf`` command in the documents' code blocks names a real subcommand and real options.

    Parsed only (nothing runs): a renamed option or subcommand would otherwise leave a README command that fails.
    """
    from roigsf_ros.cli import build_parser

    parser = build_parser()
    commands = documented_roigsf_commands(path)
    assert commands, f"no roigsf command found in {path.name}"
    refused = []
    for command in commands:
        try:
            parser.parse_args(shlex.split(command)[1:])
        except SystemExit:
            refused.append(command)
    assert refused == []


@pytest.mark.parametrize("command", ["bench", "targets"])
def test_the_readmes_synopsis_names_every_option_of_the_benchmark_commands(command: str) -> None:
    """The README's ``roigsf bench`` / ``roigsf targets`` lines are what a user copies from: an option missing there
    (``--max-frames``, ``--eval-every``, the targets' margins were) is an option nobody finds."""
    import argparse

    from roigsf_ros.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    camera = {a for g in sub._action_groups if g.title == "camera topics (bags)" for a in g._group_actions}
    options = {s for a in sub._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
    options -= {s for a in camera for s in a.option_strings if s != "--realsense"}  # "roigsf map's camera options"
    lines = [c for c in documented_roigsf_commands(ROOT / "README.md") if c.startswith(f"roigsf {command} ")]
    named = {token.split("=")[0] for line in lines for token in line.split() if token.startswith("--")}
    assert sorted(options - named) == []


def test_the_readme_module_table_lists_each_layers_modules() -> None:
    """The README's "What is here" table names, per layer, modules that exist, and every one of them unless the row
    ends its list with "..." (the nodes' helpers): a module added or renamed without the table fails here."""
    rows = re.findall(r"^\| `(\w+)/` \| ([^|]+) \|", (ROOT / "README.md").read_text(), flags=re.M)
    assert len(rows) >= 10, rows
    for layer, cell in rows:
        listed = re.findall(r"`(\w+)`", cell)
        present = {p.stem for p in (ROOT / "roigsf_ros" / layer).glob("*.py")} - {"__init__", "__main__"}
        assert set(listed) <= present, f"{layer}/: the README names {sorted(set(listed) - present)}, not modules"
        if "..." not in cell:
            assert set(listed) == present, f"{layer}/: the README's table leaves out {sorted(present - set(listed))}"


def test_the_readme_recommends_the_variant_the_library_names() -> None:
    """The README's "Which policy to use" recommends, for choosing among candidate poses, the pool spec whose parameters
    are ``RECOMMENDED_UNSEEN`` (what the kernel warm-up compiles for and ``roigsf perf nbv`` times): a recommendation
    changed in one place and not the other would leave the warm-up or the figures on a variant nobody recommends."""
    from roigsf_ros.experiments.bench import parse_policies
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN

    section = (ROOT / "README.md").read_text().split("### Which policy to use", 1)[1].split("\n## ", 1)[0]
    pool = section.split("- **Choosing keyframes in a stream**", 1)[0]
    spec_text = re.search(r"`(roi-gsurfisher:[^`]+)`", pool)
    assert spec_text, "no roi-gsurfisher spec in the README's recommendation for choosing views"
    (spec,) = parse_policies(spec_text.group(1), "pool")
    assert spec.params == dict(RECOMMENDED_UNSEEN), (spec_text.group(1), dict(RECOMMENDED_UNSEEN))


def test_the_readme_recommends_the_stream_variant_the_library_names() -> None:
    """The same for choosing keyframes in a stream: the README's first spec there is ``RECOMMENDED_STREAM_POLICY``
    with ``RECOMMENDED_STREAM`` (what config/recommended/stream.yaml holds), on a mapper with
    ``RECOMMENDED_STREAM_MAPPER``."""
    from roigsf_ros.experiments.bench import parse_policies
    from roigsf_ros.policies import RECOMMENDED_STREAM, RECOMMENDED_STREAM_MAPPER, RECOMMENDED_STREAM_POLICY

    section = (ROOT / "README.md").read_text().split("### Which policy to use", 1)[1].split("\n## ", 1)[0]
    stream = section.split("- **Choosing keyframes in a stream**", 1)[1].split("\n- ", 1)[0]
    spec_text = re.search(r"`(roi-gsurfisher:[^`]+)`", stream)
    assert spec_text, "no roi-gsurfisher spec in the README's recommendation for choosing keyframes"
    (spec,) = parse_policies(spec_text.group(1), "stream")
    assert (spec.name, spec.params) == (RECOMMENDED_STREAM_POLICY, dict(RECOMMENDED_STREAM)), spec_text.group(1)
    for name, value in RECOMMENDED_STREAM_MAPPER.items():
        assert f"`{name}: {value}`" in " ".join(stream.split()), f"the stream recommendation leaves out {name}: {value}"


def test_the_readmes_library_example_scores_a_saved_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's "NBV scoring (library)" Python block runs as written on a small saved map and a traj.txt."""
    import contextlib
    import io

    import numpy as np

    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.mapping import Mapper, MapperConfig
    from roigsf_ros.perf.io import make_synthetic_replica

    section = (ROOT / "README.md").read_text().split("## NBV scoring (library)", 1)[1].split("\n## ", 1)[0]
    (code,) = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    intr = make_synthetic_replica(tmp_path / "scene", 48, 36, 6, seed=1)
    frames = list(ReplicaSequence(tmp_path / "scene"))
    mapper = Mapper(intr, MapperConfig(iters_per_keyframe=4, track_h_train=False))
    for f in frames[::2]:
        mapper.add_keyframe(f)
    monkeypatch.chdir(tmp_path)
    mapper.save(tmp_path / "runs" / "map")
    np.savetxt("traj.txt", np.stack([f.T_wc.reshape(16) for f in frames[1::2]]))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    best, *_, status = out.getvalue().split()
    assert best in {"0", "1", "2"} and status == "ok", out.getvalue()
