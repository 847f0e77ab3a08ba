"""The wire contract: pydantic models, estimator parameters, error bodies and the round
(dataset) format with its local metric frame. Imports nothing else of ours."""
