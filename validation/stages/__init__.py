"""The stages of a validation run: each is ``stage(context) -> None``
(context.py). common.py holds those every run shares; scene.py the scene
comparison's; speed.py its speed-and-images stage; quadrature.py the
estimators of N directions'; cases.py a failure case's and a parameter
sweep's. The pipeline lists them in order (pipeline.py)."""
