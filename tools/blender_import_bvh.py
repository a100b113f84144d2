"""Imports a BVH file into Blender, working around Debian Blender 3.4's broken menu import.

    blender --python tools/blender_import_bvh.py -- motion.bvh          # opens it in the UI
    blender -b --python tools/blender_import_bvh.py -- motion.bvh        # headless

Blender 3.4's BVH importer opens files with mode 'rU', which the Python 3.11 it ships with
rejects ("invalid mode: 'rU'"), so File > Import > Motion Capture (.bvh) fails there. This
script maps the mode to 'r' around the import (nothing else changes) and uses the importer's
defaults (forward -Z, up Y, scale 1), as the menu does. Other Blender versions import from the
menu directly.
"""
import builtins
import sys


def import_bvh(path, **options):
    """Runs bpy.ops.import_anim.bvh on `path` with the 'rU' mode mapped to 'r'."""
    import bpy

    real_open = builtins.open

    def open_without_u(file, mode="r", *args, **kwargs):
        if isinstance(mode, str) and "U" in mode:
            mode = mode.replace("U", "") or "r"
        return real_open(file, mode, *args, **kwargs)

    builtins.open = open_without_u
    try:
        return bpy.ops.import_anim.bvh(filepath=path, **options)
    finally:
        builtins.open = real_open


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) != 1:
        print("usage: blender --python tools/blender_import_bvh.py -- FILE.bvh")
        sys.exit(2)
    result = import_bvh(argv[0])
    print(f"blender_import_bvh: {argv[0]}: {sorted(result)}")
