#!/usr/bin/env python3
"""Writes the linear scene of a nonsmooth one with the slack cables of a
result removed: the structure an active-set step of the nonsmooth cg solves
(BENCHMARKS.md, the 30³ nonsmooth tower).

    nsdd solve t30n.toml --out t30n_d.json
    python3 benches/tools/drop_slack_cables.py t30n.toml t30n_d.json t30r.toml

Python 3.11+ (tomllib), no other package. Keeps nodes, supports and loads;
writes only what the scene format needs for a linear solve.
"""
import json
import sys
import tomllib


def toml_array(values):
    if values and isinstance(values[0], str):
        return "[" + ", ".join('"%s"' % v for v in values) + "]"
    return "[" + ", ".join(repr(v) for v in values) + "]"


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    scene_path, result_path, out_path = sys.argv[1:]
    with open(scene_path, "rb") as f:
        scene = tomllib.load(f)
    with open(result_path) as f:
        slack = json.load(f)["slack"]
    elements = scene["elements"]
    if len(slack) != len(elements["a"]):
        sys.exit("the result has %d elements, the scene %d" % (len(slack), len(elements["a"])))
    keep = [i for i, s in enumerate(slack) if not s]
    parts = ['[scene]\nname = "%s-without-slack-cables"\n' % scene["scene"]["name"],
             "[effects]\nunilateral_cables = false\n"]
    parts.append("[nodes]\n" + "\n".join("%s = %s" % (k, toml_array(v)) for k, v in scene["nodes"].items()) + "\n")
    parts.append("[elements]\n" + "\n".join(
        "%s = %s" % (k, toml_array([v[i] for i in keep])) for k, v in elements.items()) + "\n")
    for section in ("supports", "loads"):
        if section in scene:
            parts.append("[%s]\n" % section + "\n".join(
                "%s = %s" % (k, toml_array(v)) for k, v in scene[section].items()) + "\n")
    with open(out_path, "w") as f:
        f.write("\n".join(parts))
    print("wrote %s (%d of %d elements)" % (out_path, len(keep), len(slack)))


if __name__ == "__main__":
    main()
