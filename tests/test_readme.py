"""The README's Python example runs as written (doctest), and every ``python train.py`` line of
it composes and passes the option checks as copied."""

from __future__ import annotations

import doctest
import re
import shlex

import pytest

from tests.helpers import REPO


def test_the_readme_python_example_runs():
    text = (REPO / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL) if ">>>" in b]
    assert blocks, "README.md has no Python example"
    parser, runner = doctest.DocTestParser(), doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for k, block in enumerate(blocks):
        runner.run(parser.get_doctest(block, {}, f"README.md python block {k}", "README.md", 0))
    failed, tried = runner.summarize(verbose=False)
    assert tried > 0 and failed == 0


def readme_train_commands() -> list[str]:
    """Every ``python train.py ...`` line of the README's shell blocks, comment dropped."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL)
    lines = [line.split("#")[0].strip() for block in blocks for line in block.splitlines()]
    return [line.split("&&")[-1].strip() for line in lines if "python train.py" in line]


@pytest.mark.parametrize("command", readme_train_commands())
def test_every_readme_train_command_composes_and_passes_the_option_checks(command):
    """The README's runs are valid as copied: Hydra composes their overrides (groups, keys,
    launchers) and the options pass the rule table (placeholders like DIR are plain strings)."""
    from omegaconf import OmegaConf

    from flamerecon.fit.option_rules import check_options
    from flamerecon.run.cli import compose_train

    overrides = [o for o in shlex.split(command)[2:] if o != "-m" and not o.startswith("resume=")]
    overrides = [o.split(",")[0] if o.startswith("solver.l1_rel=") else o for o in overrides]  # one job of a sweep
    cfg = compose_train([re.sub(r"'?range\((\d+),.*\)'?", r"\1", o) for o in overrides], default_scene=None)
    check_options(OmegaConf.to_container(cfg, resolve=False))
