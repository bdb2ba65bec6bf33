"""The kernels compiled ahead of time into one extension module, `_compiled`, beside their sources.

    python -m tecdard.control.estimators.kernels.build [OUT_DIR]     (`tecdard warm` runs it)

numba's ahead-of-time compiler (numba.pycc) compiles the kernels the estimators call (PUBLIC, with
every kernel they call compiled into them) for their signatures, with the JIT's options (`nogil`,
`error_model="numpy"`) and the same code generator, into a C extension that needs numpy and
nothing of numba or LLVM at run time. A daemon that loads it imports no numba (about 180 MB of
RSS and 1.5 s of start less) and maps no memory both writable and executable, so its unit can
take MemoryDenyWriteExecute. The kernels' sources are digested into `_compiled.digest`;
`kernels.api` loads the module only while the digest is still theirs (aot_problem), and runs
numba's JIT otherwise (a kernel edited since, or an install without a C compiler).
"""
from __future__ import annotations

import contextlib
import glob
import hashlib
import importlib
import importlib.util
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
MODULE = "_compiled"
DIGEST_FILE = os.path.join(HERE, MODULE + ".digest")
SOURCES = ("__init__.py", "constants.py", "linalg.py", "records.py", "nbtypes.py", "report.py", "model.py",
           "evidence.py", "run.py")
KERNEL_MODULES = ("linalg", "report", "model", "evidence", "run")
# what the estimators call, per kernel module: the exported functions (their callees are compiled into them)
PUBLIC = {
    "run": ("ekf_advance", "ekf_segments"),
    "report": ("eta_evidence", "eta_weight", "report_state", "report_states", "plane_rotation", "rate_moments",
               "rotation_axes", "output_ends", "segment_moments"),
    "evidence": ("position_increment", "position_reset", "position_residual", "position_sums"),
    "model": ("block_update",),
}


def source_digest() -> str:
    """sha256 of the kernels' sources (the extension needs numpy alone, whichever numba built it)."""
    h = hashlib.sha256()
    for name in SOURCES:
        with open(os.path.join(HERE, name), "rb") as f:
            h.update(name.encode() + b"\n" + f.read())
    return h.hexdigest()


def aot_problem() -> str | None:
    """Why the ahead-of-time build would not be used (None: it is current)."""
    try:
        with open(DIGEST_FILE, encoding="ascii") as f:
            built = f.read().strip()
    except OSError:
        return "not built (`tecdard warm` builds it)"
    if built != source_digest():
        return "built from other sources than these (`tecdard warm` rebuilds it)"
    if importlib.util.find_spec(f"{__package__}.{MODULE}") is None:
        return "its extension module is missing (`tecdard warm` rebuilds it)"
    return None


CPU_ENV = "TECDAR_KERNELS_CPU"   # the CPU the build targets: "host" (default), "generic", or an LLVM CPU name
PR_GET_MDWE = 66               # prctl: the process's memory-deny-write-execute flags (Linux 6.3+)


def write_execute_denied() -> bool:
    """Whether this process may not create executable memory (PR_SET_MDWE: systemd's
    MemoryDenyWriteExecute on kernels that have it), which numba's JIT needs. False where the
    kernel cannot tell."""
    try:
        import ctypes
        return ctypes.CDLL(None, use_errno=True).prctl(PR_GET_MDWE, 0, 0, 0, 0) > 0
    except (OSError, AttributeError):
        return False


def export_name(module: str, name: str) -> str:
    return f"{module}__{name}"


@contextlib.contextmanager
def _ir_only():
    """numba's JIT without its machine code. The kernel modules' import compiles every kernel through
    its dispatcher, which finalises each library and has LLVM's MCJIT generate machine code for it: a
    third of the build (15 of 48 s profiled), and nothing here ever calls it. pycc needs only the
    finalised, optimised IR of each library, which it links into the extension and compiles once.
    Within this block a library is finalised and optimised as ever, but never handed to MCJIT, and
    its functions' addresses are a placeholder no one calls (the exports are pycc's own machine code)."""
    from numba.core import codegen

    def finalize_ir(self):
        self._codegen._scan_and_fix_unresolved_refs(self._final_module)

    def no_address(self, name):
        self._ensure_finalized()
        return _NO_ADDRESS

    patched = {(codegen.JITCodeLibrary, "_finalize_specific"): finalize_ir,
               (codegen.JITCodeLibrary, "get_pointer_to_function"): no_address,
               (codegen.JITCPUCodegen, "_add_module"): lambda self, module: None,
               (codegen.JITCPUCodegen, "set_env"): lambda self, env_name, env: None,    # a global of machine code
               # each library links in all it calls and optimises the lot, again for every caller: the
               # extension's module, all of them linked, is optimised once by pycc
               (codegen.JITCodeLibrary, "_optimize_final_module"): lambda self: None}
    saved = {key: getattr(*key) for key in patched}
    for (cls, name), fn in patched.items():
        setattr(cls, name, fn)
    try:
        yield
    finally:
        for (cls, name), fn in saved.items():
            setattr(cls, name, fn)


_NO_ADDRESS = 1        # never called: a build process exits once the extension is written


def build(out_dir: str = HERE) -> float:
    """Compile every kernel with a signature into `out_dir`/_compiled*.so and write the digest; the seconds."""
    t0 = time.monotonic()
    from numba.core.compiler import Flags
    from numba.pycc import CC, compiler as pycc_compiler

    class KernelFlags(Flags):          # pycc's defaults are Python's error model and the GIL held
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.error_model = "numpy"
            self.release_gil = True

    from tecdard.control.estimators import kernels
    kernels.BUILDING = True
    kernels.EXPORTS.clear()
    try:
        with _ir_only():
            for name in KERNEL_MODULES:
                importlib.import_module(f"{kernels.__name__}.{name}")
    finally:
        kernels.BUILDING = False
    digest = source_digest()
    cc = CC(MODULE)
    cc.verbose = False
    # for this machine's CPU, as the JIT compiles (pycc's default is a generic x86-64, some 15 % slower
    # on the long loops): the build is made where it runs, by the install; without fast-math neither
    # contracts or reorders arithmetic, so the answers are the JIT's to the last digit
    # (TECDAR_KERNELS_CPU=generic: any CPU of this architecture, for a wheel that other machines install)
    cpu = os.environ.get(CPU_ENV, "host")
    cc.target_cpu = "" if cpu == "generic" else cpu
    with tempfile.TemporaryDirectory() as tmp:
        cc.output_dir = tmp
        for module, name, signature, fn in kernels.EXPORTS:
            if name in PUBLIC.get(module, ()):
                cc.export(export_name(module, name), signature)(fn)
        saved = pycc_compiler.Flags
        pycc_compiler.Flags = KernelFlags
        try:
            cc.compile()
        finally:
            pycc_compiler.Flags = saved
        os.makedirs(out_dir, exist_ok=True)
        for old in glob.glob(os.path.join(out_dir, MODULE + ".*.so")):
            os.remove(old)
        for built in glob.glob(os.path.join(tmp, MODULE + ".*")):
            shutil.move(built, os.path.join(out_dir, os.path.basename(built)))
    with open(os.path.join(out_dir, MODULE + ".digest"), "w") as f:
        f.write(digest + "\n")
    return time.monotonic() - t0


if __name__ == "__main__":
    took = build(sys.argv[1] if len(sys.argv) > 1 else HERE)
    print(f"compiled the estimator's kernels ahead of time in {took:.1f} s")
