"""Rewrite the wheel builder's Python/numpy include paths in the venv's CMake files.

The ros-jazzy-* wheels were built under /opt/python/cp3XX-cp3XX/ (manylinux), and the
exported ``*__rosidl_generator_pyExport.cmake`` files under ``$VIRTUAL_ENV/share``
still list that interpreter's include directories in INTERFACE_INCLUDE_DIRECTORIES.
CMake refuses imported targets whose include directories do not exist, so building
any interface package that depends on them (our msg_defs/) fails. Point them at this
interpreter's headers and this venv's numpy headers instead. Idempotent.

Usage: python tools/fix_cmake_includes.py [PREFIX]   (default: sys.prefix)
"""
import os
import re
import sys
import sysconfig

import numpy

PY_INCLUDE = re.compile(r"/opt/python/cp3\d+-cp3\d+/include/python3\.\d+")
NP_INCLUDE = re.compile(
    r"/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+/site-packages/numpy/(?:_core|core)/include")


def main() -> int:
    prefix = sys.argv[1] if len(sys.argv) > 1 else sys.prefix
    share = os.path.join(prefix, "share")
    py_inc = sysconfig.get_paths()["include"]
    np_inc = numpy.get_include()
    if not os.path.isfile(os.path.join(py_inc, "Python.h")):
        print(f"error: Python.h not found in {py_inc} (install the Python dev headers)",
              file=sys.stderr)
        return 1
    changed = 0
    for root, _dirs, files in os.walk(share):
        for name in files:
            if not name.endswith(".cmake"):
                continue
            path = os.path.join(root, name)
            with open(path, encoding="utf-8", errors="surrogateescape") as f:
                text = f.read()
            if "/opt/python/cp3" not in text:
                continue
            new = NP_INCLUDE.sub(np_inc, text)
            new = PY_INCLUDE.sub(py_inc, new)
            if new != text:
                with open(path, "w", encoding="utf-8", errors="surrogateescape") as f:
                    f.write(new)
                changed += 1
    print(f"fixed include paths in {changed} cmake file(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
