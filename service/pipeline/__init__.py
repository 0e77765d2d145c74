"""The live runtime behind ``meniscope serve`` and ``meniscope bench serve``: source to fitted windows.

:mod:`.supervisor` keeps a :mod:`.runtime` pipeline running for a :class:`~service.server.settings.ServiceSettings`
and hands fitted windows, trace snippets and timings to a sink. Nothing is imported here, so that the
fit worker processes (:mod:`.fitting`) load only what fitting needs.
"""
