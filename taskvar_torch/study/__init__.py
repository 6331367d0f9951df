"""The study beside the library: the commands that run and summarise many trainings (the scale
study, ``taskvar report``, ``taskvar sweep``), built on the library's public names only
(tests/study/test_study_boundary.py). The library imports nothing from it.
"""
