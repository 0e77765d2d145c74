"""The live runtime behind ``meniscope serve`` and ``meniscope bench serve``: source to fitted windows.

:class:`Supervisor` keeps a :class:`Pipeline` running for a :class:`~service.settings.ServiceSettings`
and hands :class:`FittedWindow` s, :class:`TraceSnippet` s and timings to a :class:`PipelineSink`.
"""
from service.pipeline.runtime import FittedWindow, LatestFrame, Pipeline, PipelineSink, PipelineStats, TraceSnippet
from service.pipeline.supervisor import Health, Supervisor

__all__ = ["FittedWindow", "Health", "LatestFrame", "Pipeline", "PipelineSink", "PipelineStats", "Supervisor",
           "TraceSnippet"]
