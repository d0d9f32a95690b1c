"""The README's Python example runs as written (doctest)."""

from __future__ import annotations

import doctest
import re

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
