"""The HTTP transport: FastAPI app, routers, SSE, auth, viewer."""
