"""The paper's tables and figures in one resumable run (:mod:`~stnh_tf.paper.reproduce`), its
figures (:mod:`~stnh_tf.paper.figures`), and the offline demo (:mod:`~stnh_tf.paper.demo`)."""
