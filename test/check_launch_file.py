#!/usr/bin/env python3
"""Checks the installed launch file without ROS: `launch` and `launch_ros` are not on PyPI
(the PyPI project named `launch` is another one), so no LaunchDescription is built here.
Instead, in share/vernier_ros/launch_scripts/detector.launch.py under PREFIX:
  * it compiles (Python syntax);
  * every package it imports is an <exec_depend> of package.xml;
  * it defines generate_launch_description();
  * its Node(...) starts package vernier_ros's executable `detector`, present in
    PREFIX/lib/vernier_ros/ (what `ros2 launch` would run).

    check_launch_file.py PREFIX   (install/vernier_ros of a colcon workspace)"""

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def main():
    prefix = Path(sys.argv[1])
    share = prefix / "share" / "vernier_ros"
    path = share / "launch_scripts" / "detector.launch.py"
    tree = ast.parse(path.read_text(), str(path))
    compile(tree, str(path), "exec")
    depends = {e.text.strip() for e in ET.parse(share / "package.xml").iter("exec_depend")}
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            imported.add(node.module.split(".")[0])
    undeclared = imported - depends - set(sys.stdlib_module_names)
    assert not undeclared, f"imported but not <exec_depend>: {sorted(undeclared)}"
    functions = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions, "no generate_launch_description()"
    nodes = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and getattr(n.func, "id", None) == "Node"]
    assert len(nodes) == 1, f"{len(nodes)} Node(...) actions"
    kwargs = {k.arg: k.value.value for k in nodes[0].keywords
              if isinstance(k.value, ast.Constant)}
    assert kwargs.get("package") == "vernier_ros", kwargs
    executable = prefix / "lib" / "vernier_ros" / kwargs.get("executable", "")
    assert executable.is_file(), f"{executable} not installed"
    print(f"PASS launch file: syntax, imports {sorted(imported)} declared, starts {executable}")


if __name__ == "__main__":
    main()
