"""`jaxdyn scenes`: list the built-in scenes."""

import json

HELP = "list the built-in scenes"


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    from .._scenefile import builtin_scenes

    scenes = builtin_scenes()
    if args.json:
        print(json.dumps(scenes, indent=2))
    else:
        width = max(map(len, scenes))
        for name, description in scenes.items():
            print(f"{name:<{width}}  {description}")
    return 0
