"""The job, top to bottom: sensor models -> stereo -> filters -> orthoimages -> assessment.

Split by concern (issue #23): :mod:`.inputs` (images, models, seed DEM), :mod:`.tiles`
(tile execution and cache), :mod:`.stages` (one function per stage; the assessment's in
:mod:`.assessment`), :mod:`.job`
(``stereodem run``), :mod:`.record` (``run.json``: timings, memory, versions).
"""
