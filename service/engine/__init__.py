"""Robot sessions: the localization service, localizers, session stores, map admin, events,
metrics."""
