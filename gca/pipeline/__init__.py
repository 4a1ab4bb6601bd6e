"""gca.pipeline: the glue between the DVC stages and the library (one layer below ``stages/``).

The only library layer that reads ``params`` (the resolved ``params.yaml`` mapping): it turns them into the
typed configs the library takes, finds each stage's inputs on disk, and mirrors runs to MLflow (``track``).
``grid`` runs the ``dvc.yaml`` stage commands of a scene x method grid without dvc. Everything below it
(``gca.train``, ``gca.eval``, ...) takes typed values. Layer order: ``docs/architecture.md``.
"""
