"""Every command-line option that names a placeholder (metavar) also names itself ("--views"): typer
before 0.28 builds an option without explicit names as --<METAVAR> when the placeholder is the
parameter's name in capitals, so `eval --views` became `eval --VIEWS` there (typer 0.27.2)."""

import ast
from pathlib import Path

CLI = Path(__file__).resolve().parent.parent / "nanogs_warp" / "cli"


def options_with_a_placeholder():
    for path in sorted(CLI.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "Option"
                    and any(k.arg == "metavar" for k in node.keywords)):
                yield path.name, node


def test_options_with_a_placeholder_name_themselves():
    found = list(options_with_a_placeholder())
    assert len(found) >= 20  # the walk sees the commands' options
    unnamed = [
        f"{name}:{node.lineno}" for name, node in found
        if not (node.args and isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith("-"))
    ]  # fmt: skip
    assert unnamed == []
