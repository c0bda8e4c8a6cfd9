r"""Run the README's example as written and measure its estimate: the error of ``H`` against the
example's ``h_true`` at the 512 x 512 image corners, for ``estimate_images``' default and the
other presets, also with an exposure change of image_b (its intensities times 0.6, plus 40).

  python -m experiments.readme_example [--json_out=docs/readme_example.json]

Prints one JSON object: per preset (``default``: what the README calls, no options;
``estimate_default``: ``EstimateOptions()``; ``network_only``) the error in px and the flag, on
the plain pair and with the exposure change; the identity's error; the machine and code.
"""

from __future__ import annotations

import os
import re

from absl import app, flags

from experiments import common, flags_common
from stnh_tf.paper import current_results

flags_common.define_json_out()
FLAGS = flags.FLAGS
EXPOSURE = (0.6, 40.0)
"""image_b's exposure change: ``gain * b + offset`` (uint8, clipped)."""


def readme_code() -> str:
    """The README's first Python code block (its example), as written."""
    with open(os.path.join(current_results.default_root(), "README.md")) as f:
        text = f.read()
    match = re.search(r"```python\n(.*?)```", text, re.S)
    if match is None:
        raise ValueError("README.md has no ```python block.")
    return match.group(1)


def measure() -> dict:
    """The example run as written (one call of each preset on its pair); see the module doc."""
    import numpy as np

    from stnh_tf.evaluation import benchmarks
    from stnh_tf.evaluation.camera_pairs import image_errors
    from stnh_tf.inference import EstimateOptions

    scope = {}
    exec(compile(readme_code(), "README.md", "exec"), scope)  # noqa: S102 - the doc's own code
    est, a, b, h_true = scope["est"], scope["image_a"], scope["image_b"], scope["h_true"]
    size = a.shape[1], a.shape[0]
    gain, offset = EXPOSURE
    exposed = np.clip(gain * b.astype(np.float32) + offset, 0, 255).astype(np.uint8)
    error = lambda h: float(image_errors(h[None], h_true[None], size)[0])  # noqa: E731
    out = {"readme_H_error_px": error(scope["H"]), "identity_error_px": error(np.eye(3)),
           "exposure": {"gain": gain, "offset": offset}}
    presets = {"default": None, "estimate_default": EstimateOptions(),
               "network_only": EstimateOptions.network_only()}
    for name, options in presets.items():
        out[name] = {}
        for case, image_b in (("plain", b), ("exposure", exposed)):
            info = est.estimate_images_with_info(a, image_b, options)
            out[name][case] = {"error_px": error(info.homography[0]),
                               "implausible": bool(info.implausible[0])}
    out["machine"] = benchmarks.machine_info()
    return out


def main(argv):
    del argv
    with common.user_errors("readme_example"):
        result = measure()
    common.emit_json(result, FLAGS.json_out)


if __name__ == "__main__":
    app.run(main)
