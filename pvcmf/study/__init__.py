"""Validation studies and parameter sweeps on top of the pipeline and the truth.

* :mod:`pvcmf.study.statistics` - error statistics and face regions;
* :mod:`pvcmf.study.from_ct` - judging a prediction against a post-operative CT;
* :mod:`pvcmf.study.validation` - paper 000's study (:func:`run_study`,
  :func:`study_predictor`); :mod:`pvcmf.study.predictions` - its predictions' on-disk
  cache;
* :mod:`pvcmf.study.parameters`, :mod:`pvcmf.study.evaluation`,
  :mod:`pvcmf.study.pipeline_evaluation`, :mod:`pvcmf.study.engine`,
  :mod:`pvcmf.study.tables`, :mod:`pvcmf.study.cli` - parameter sweeps (paper 001) on
  Dask (:func:`pvcmf.study.engine.sweep`).

Submodules are imported on use, so ``import pvcmf.study.statistics`` does not load the
pipeline.
"""
