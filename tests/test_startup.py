"""Start-up stays instant: the parser, ``--help`` and argument errors load no heavy package."""

import subprocess
import sys

import pytest

HEAVY = ("torch", "kornia", "onnx", "onnxscript", "matplotlib", "scipy", "cv2")


def loaded_after(code: str) -> list[str]:
    """Heavy modules in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return eval(proc.stdout.strip().splitlines()[-1])


def test_import_torchmetal_is_light():
    assert loaded_after("import torchmetal") == []


def test_building_and_parsing_loads_nothing_heavy():
    code = "\n".join([
        "import torchmetal.cli as cli",
        "p = cli.build_parser()",
        "for argv in (['fit', 'cap', '-o', 'mat'], ['render', 'm', '--light', '0 0 1 0', '--camera', '0 0 1 0', '-o', 'x.png'],",
        "             ['export', 'm'], ['synth', '-o', 's'], ['demo', '--quick'], ['bench']):",
        "    args = p.parse_args(argv)",
        "    assert callable(args.func)",
    ])
    assert loaded_after(code) == []


@pytest.mark.parametrize("argv", [
    ["--help"], ["fit", "--help"], ["render", "--help"], ["export", "--help"], ["synth", "--help"], ["demo", "--help"],
    ["render", "m", "--light", "1 2", "--camera", "0 0 1 0", "-o", "x.png"],  # argument error
    ["nonsense"],
])
def test_help_and_argument_errors_load_nothing_heavy(argv):
    code = "\n".join([
        "import torchmetal.cli as cli",
        f"try:\n    cli.main({argv!r})\nexcept SystemExit as e:\n    print('exit', e.code)",
    ])
    assert loaded_after(code) == []


def test_torchmetal_help_exits_zero():
    proc = subprocess.run([sys.executable, "-m", "torchmetal", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "usage: torchmetal" in proc.stdout


def test_lazy_package_exports_still_resolve():
    code = "\n".join([
        "import torchmetal as tm",
        "names = [n for n in tm.__all__ if getattr(tm, n) is None]",
        "assert not names, names",
        "from torchmetal.renderer import MaterialRenderer",
        "from torchmetal.material import save_material",
        "assert tm.MaterialRenderer is MaterialRenderer and tm.save_material is save_material",
        "assert tm.io.capture.load_capture is tm.load_capture and 'MaterialRenderer' in dir(tm)",
        "from torchmetal import *",
        "try:\n    tm.no_such_name\nexcept AttributeError:\n    pass\nelse:\n    raise AssertionError('no AttributeError')",
    ])
    assert "torch" in loaded_after(code)  # resolving the names loads the library, as it should
