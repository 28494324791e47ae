"""`jaxdyn scenes`: list the built-in scenes, or every body's and effect's inputs."""

import json

HELP = "list the built-in scenes (--parameters: what scene files and --set accept)"


def add_arguments(parser) -> None:
    parser.add_argument("--parameters", action="store_true",
                        help="list every body's and effect's inputs: name, allowed values "
                             "and unit, default, meaning (as declared by each)")
    parser.add_argument("--markdown", action="store_true",
                        help="with --parameters: the README's tables")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    if args.parameters:
        return _parameters(args.json, args.markdown)
    from .._scenefile import builtin_scenes

    scenes = builtin_scenes()
    if args.json:
        print(json.dumps(scenes, indent=2))
    else:
        width = max(map(len, scenes))
        for name, description in scenes.items():
            print(f"{name:<{width}}  {description}")
    return 0


def _parameters(as_json: bool, as_markdown: bool) -> int:
    from .._inputs import all_registered, markdown, table

    bodies, effects = all_registered()
    if as_markdown:
        print(markdown(), end="")
        return 0
    out = {"bodies": {k: table(c) for k, c in sorted(bodies.items())},
           "effects": {k: table(c) for k, c in sorted(effects.items())}}
    if as_json:
        print(json.dumps(out, indent=2))
        return 0
    for group, title in (("bodies", "body = "), ("effects", "[[effects]] type = ")):
        for kind, rows in out[group].items():
            print(f"{title}{kind!r}")
            prefix = "" if group == "bodies" else f"{kind}."
            for row in rows:
                default = row["default"] if row["default"] in ("required", "optional") \
                    else f"default {row['default']}"
                print(f"  {prefix}{row['name']}: {row['allowed']}; {default}. {row['meaning']}")
    return 0
