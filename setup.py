"""The optional compiled part of the library; everything else is in pyproject.toml.

``registration._cpd._ckernel`` (CPD's compiled passes: the E-step, dense and truncated, the
correspondences, kernel products and low-rank factor with a vectorised exp, the low-rank
M-step, and the nearest neighbours of e and the similarity's ICP; plain C through the
buffer protocol, no numpy headers) is built when a C compiler is present.
Without one the install still succeeds (``optional=True``) and the library runs the same
computation with numpy (`registration.compiled_kernel()` says which is in use).
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class BuildExt(build_ext):
    def build_extensions(self) -> None:
        if self.compiler.compiler_type == "unix":
            # no errno or floating-point traps to honour: lets the loops vectorise
            # (-fopenmp-simd: the `omp simd` reductions only, no OpenMP runtime)
            for ext in self.extensions:
                ext.extra_compile_args += ["-O3", "-fno-math-errno", "-fno-trapping-math",
                                         "-fopenmp-simd"]
        super().build_extensions()


setup(
    ext_modules=[Extension("registration._cpd._ckernel", ["registration/_cpd/_ckernel.c"],
                           optional=True)],
    cmdclass={"build_ext": BuildExt},
)
