"""mcillum validation: compare the estimators with Mitsuba's path tracer.

The package reads top to bottom as a pipeline, one module per stage:

    scenes (scenes/*.xml) → renders → statistics → (report, later issues)

``images`` holds the file formats every stage reads and writes. Modules only
import stages above them.
"""
