r"""Draw Fig. 4 again from a reproduction's committed JSON, without training or evaluating.

  python -m experiments.render_fig4 --reproduce_dir=docs/reproduce_cpu

Reads ``results.json`` of ``--reproduce_dir`` (written by ``experiments.reproduce``), the paper
recipe's and the paper's-schedule model cards, and writes ``figures/fig4_mace_bars.png`` there
(or ``--output``): the bars labelled as assembled where they are, the degenerate-prediction
rule's marks, Table 1's seeds as dots, the paper's-schedule bars
(:mod:`stnh_tf.paper.fig4_render`). Prints ``{"output", "marks_from", "label"}``.
"""

from __future__ import annotations

import json

from absl import app, flags

from experiments import common

flags.DEFINE_string("reproduce_dir", None, "A folder written by experiments.reproduce.",
                    required=True)
flags.DEFINE_string("output", None, "PNG to write (default: <reproduce_dir>/figures/"
                    "fig4_mace_bars.png).")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    from stnh_tf.paper import fig4_render

    with common.user_errors("render_fig4", errors=(ValueError, OSError, KeyError)):
        if FLAGS.output and not FLAGS.output.lower().endswith(".png"):
            raise ValueError(f"--output is the PNG to write, ending in .png; received "
                             f"{FLAGS.output!r}.")
        print(json.dumps(fig4_render.render(FLAGS.reproduce_dir, FLAGS.output)))


if __name__ == "__main__":
    app.run(main)
