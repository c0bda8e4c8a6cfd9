r"""The "current results" tables of BENCHMARKS.md and README.md, generated from the project's JSON
(:mod:`stnh_tf.paper.current_results` says which JSON and how).

  python -m experiments.current_results            # print both tables
  python -m experiments.current_results --write    # rewrite them in BENCHMARKS.md and README.md
  python -m experiments.current_results --check    # exit 1 naming each file whose table differs
"""

from __future__ import annotations

import sys

from absl import app, flags

from experiments import common
from stnh_tf.paper import current_results

flags.DEFINE_string("root", None, "Repository root (default: the checkout holding stnh_tf/).")
flags.DEFINE_bool("write", False, "Rewrite the blocks of BENCHMARKS.md and README.md.")
flags.DEFINE_bool("check", False, "Exit 1, naming each file whose block differs from the JSON.")
FLAGS = flags.FLAGS


def main(argv):
    del argv
    if FLAGS.write and FLAGS.check:
        raise app.UsageError("--write and --check exclude each other.")
    action = "write" if FLAGS.write else "check" if FLAGS.check else "print"
    with common.user_errors("current_results"):
        code = current_results.run(action, FLAGS.root)
    sys.exit(code)


if __name__ == "__main__":
    app.run(main)
