"""Mixed precision on the machine at hand: whether the CPU computes bfloat16 natively (its
``/proc/cpuinfo`` flags), whether Keras computes on an accelerator, and the warning a run gets
when mixed bfloat16 may be slower than float32 there."""

from __future__ import annotations

import keras

from stnh_tf.training.config import TrainConfig

# CPU flags of native bfloat16 arithmetic: x86 AVX-512 BF16 and AMX, Arm BF16.
BFLOAT16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


def _cpuinfo_fields(cpuinfo: str, keys) -> list[str] | None:
    """The values of the ``cpuinfo`` lines whose key (lower-cased) is in ``keys``; ``None`` if the
    file cannot be read."""
    try:
        with open(cpuinfo) as f:
            text = f.read()
    except OSError:
        return None
    values = []
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() in keys:
            values.append(value.strip())
    return values


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> frozenset | None:
    """The CPU's instruction flags listed in ``cpuinfo`` (its ``flags`` lines on x86,
    ``Features`` on Arm); ``None`` if it cannot be read or lists none."""
    values = _cpuinfo_fields(cpuinfo, ("flags", "features"))
    return frozenset(flag for value in values or () for flag in value.split()) or None


def cpu_vendor(cpuinfo: str = "/proc/cpuinfo") -> str | None:
    """The x86 ``vendor_id`` in ``cpuinfo`` (``"GenuineIntel"``, ``"AuthenticAMD"``, ...);
    ``None`` if it cannot be read or lists none (as on Arm)."""
    values = _cpuinfo_fields(cpuinfo, ("vendor_id",))
    return values[0] if values else None


def cpu_has_native_bfloat16(cpuinfo: str = "/proc/cpuinfo") -> bool | None:
    """Whether the CPU lists a bfloat16 instruction flag (:data:`BFLOAT16_CPU_FLAGS`) in
    ``cpuinfo``; ``None`` if its flags cannot be read."""
    flags = cpu_flags(cpuinfo)
    return None if flags is None else bool(flags & BFLOAT16_CPU_FLAGS)


def accelerator_present() -> bool:
    """Whether the Keras backend computes on a GPU/TPU rather than the CPU."""
    backend = keras.backend.backend()
    if backend == "tensorflow":
        import tensorflow as tf

        return bool(tf.config.list_physical_devices("GPU")
                    or tf.config.list_physical_devices("TPU"))
    if backend == "jax":
        import jax

        return jax.default_backend() != "cpu"
    if backend == "torch":
        import torch

        return bool(torch.cuda.is_available())
    return False


def mixed_precision_warning(cfg: TrainConfig, cpuinfo: str = "/proc/cpuinfo") -> str | None:
    """A warning when ``cfg`` asks for mixed bfloat16 on a CPU where it may be slower than
    float32: one with no bfloat16 instructions (emulated, many times slower), or an x86 CPU with
    AVX-512 BF16 but no AMX (slower on the Intel Xeon measured, BENCHMARKS.md "The same benchmark
    on CPUs without AMX"; on the AMD EPYC Zen 4 measured there, with the same flags, it was faster,
    so AMD CPUs get no warning). ``None`` on an accelerator, with float32, on AMX or Arm BF16, on
    AMD, or where the CPU flags cannot be read."""
    if not cfg.mixed_precision or accelerator_present():
        return None
    flags = cpu_flags(cpuinfo)
    if flags is None:
        return None
    if not flags & BFLOAT16_CPU_FLAGS:
        return ("mixed_precision is on, but this CPU has no bfloat16 instructions (none of "
                f"{sorted(BFLOAT16_CPU_FLAGS)} in {cpuinfo}): bfloat16 is emulated and training "
                "is many times slower than in float32 here; consider --nomixed_precision.")
    if ("avx512_bf16" in flags and "amx_bf16" not in flags
            and cpu_vendor(cpuinfo) != "AuthenticAMD"):
        return ("mixed_precision is on, and this CPU has AVX-512 BF16 but no AMX (no amx_bf16 in "
                f"{cpuinfo}): on such an Intel Xeon a bfloat16 step was 1.6x slower than float32; "
                "time both with experiments.benchmark_training before a long run, and use "
                "--nomixed_precision if float32 is faster.")
    return None
