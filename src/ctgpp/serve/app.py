"""The HTTP side of ``ctgpp serve``: the page (``static/``) and a small JSON API over the scene sets,
the vocabulary and the queue of runs.

``GET /api/scenes``, ``GET /api/scenes/{key}``: the scenes and one drawn as data. ``GET /api/options``:
policies, phrasings, the language model's name when one is configured (never its key or address),
the limits. ``POST /api/runs``: queue a run (a :class:`~ctgpp.serve.schema.RunRequest`; a sentence
the compiler refuses is answered 422 with the closest phrasings). ``GET /api/runs/{id}``: its state
and results; ``POST /api/runs/{id}/cancel``; ``GET /api/runs/{id}/frames?since=K``: the guided
episode's steps simulated so far, from step K (streamed as each re-plan finishes);
``GET /api/runs/{id}/playback``: the finished rollout to animate; ``GET /api/runs/{id}/files/{name}``:
a file of its folder. Errors are ``{"message": ...}``.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ctgpp.io.export import EXPORT_KINDS, check_export_kind
from ctgpp.serve.job_queue import JobQueue, QueueFull
from ctgpp.serve.scenes import SceneSets
from ctgpp.serve.schema import MAX_BODY_BYTES, MAX_SENTENCE_CHARS, RunRequest
from ctgpp.serve.sentences import Refused, SentenceChecker, Vocabulary
from ctgpp.serve.worker import RunSpec

if TYPE_CHECKING:
    from ctgpp.language.llm.client import LLMConfig

log = logging.getLogger(__name__)

STATIC = Path(str(resources.files("ctgpp") / "serve" / "static"))
JOB_ID = re.compile(r"^[0-9a-f]{12}$")
FILE_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
# the page loads only its own files; images also from data: URLs (the drivable area)
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; object-src 'none'; "
                               "base-uri 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


@dataclass(frozen=True)
class ServeConfig:
    """data: the ``--data`` directories beside the embedded scenes; out: where run folders go; llm:
    the language model the server may use (None: the offline compiler only); workers: simulation
    processes; max_waiting: runs that may wait at once."""

    data: tuple[Path, ...] = ()
    out: Path = Path("ctgpp-serve")
    llm: LLMConfig | None = None
    workers: int = 1
    max_waiting: int = 16


class ApiError(Exception):
    """An answer other than 200: ``status`` and a one-line ``message`` (``extra`` goes along)."""

    def __init__(self, status: int, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.status, self.message, self.extra = status, message, extra


class BodyLimit:
    """ASGI middleware: a request whose body exceeds ``limit`` bytes is answered 413 unread."""

    def __init__(self, app: ASGIApp, limit: int = MAX_BODY_BYTES) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.limit):
            await _too_large(scope, receive, send, self.limit)
            return
        seen = 0

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.limit:
                raise HTTPException(413, f"the request is larger than {self.limit} bytes")
            return message

        await self.app(scope, limited, send)


async def _too_large(scope: Scope, receive: Receive, send: Send, limit: int) -> None:
    response = JSONResponse({"message": f"the request is larger than {limit} bytes"}, status_code=413)
    await response(scope, receive, send)


def create_app(config: ServeConfig) -> FastAPI:
    """The app: scene sets opened now, worker processes and the vocabulary started with the server."""
    scenes = SceneSets(config.data)
    jobs = JobQueue(config.out, config.llm, config.workers, config.max_waiting)
    state: dict[str, SentenceChecker] = {}

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        state["sentences"] = SentenceChecker()
        jobs.start()
        try:
            yield
        finally:
            state["sentences"].close()
            await asyncio.to_thread(jobs.stop)

    async def vocabulary() -> Vocabulary:
        return await state["sentences"].vocabulary()

    app = FastAPI(title="ctgpp playground", lifespan=lifespan, docs_url=None, redoc_url=None,
                  openapi_url=None)
    app.add_middleware(BodyLimit)

    @app.middleware("http")
    async def security_headers(request: Request, call_next: Any) -> Response:
        response: Response = await call_next(request)
        response.headers.update(SECURITY_HEADERS)
        return response

    @app.exception_handler(ApiError)
    async def api_error(_: Request, err: ApiError) -> JSONResponse:
        return JSONResponse({"message": err.message, **err.extra}, status_code=err.status)

    @app.exception_handler(HTTPException)
    async def http_error(_: Request, err: HTTPException) -> JSONResponse:
        return JSONResponse({"message": str(err.detail)}, status_code=err.status_code)

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, err: RequestValidationError) -> JSONResponse:
        first = err.errors()[0] if err.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ())[1:]) or "request"
        return JSONResponse({"message": f"{where}: {first.get('msg', 'invalid')}"}, status_code=422)

    @app.exception_handler(Exception)
    async def internal(_: Request, err: Exception) -> JSONResponse:
        log.exception("request failed")
        return JSONResponse({"message": f"internal error ({type(err).__name__})"}, status_code=500)

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/api/health")
    async def health() -> dict[str, Any]:
        checker = state.get("sentences")
        vocabulary_ready = checker is not None and checker.ready
        return {"ok": True, "workers_ready": jobs.ready, "vocabulary_ready": vocabulary_ready}

    @app.get("/api/scenes")
    async def scene_list() -> list[dict[str, Any]]:
        return scenes.listing()

    @app.get("/api/scenes/{key}")
    def scene_view(key: str, duration_s: float = Query(10.0, gt=0, le=20)) -> dict[str, Any]:
        try:
            return scenes.view(key, duration_s)
        except KeyError as err:
            raise ApiError(404, str(err.args[0])) from None
        except ValueError as err:
            raise ApiError(422, str(err)) from None

    @app.get("/api/options")
    async def options() -> dict[str, Any]:
        voc = await vocabulary()
        return {
            "policies": list(voc.policies), "phrasings": list(voc.phrasings),
            "llm": None if config.llm is None else {"model": config.llm.model},
            "exports": list(EXPORT_KINDS), "max_sentence_chars": MAX_SENTENCE_CHARS,
        }

    @app.post("/api/runs", status_code=201)
    async def submit(request: RunRequest) -> dict[str, Any]:
        voc = await vocabulary()
        spec, num_vehicles = await asyncio.to_thread(_checked, request, voc)
        if request.sentence and not request.llm:
            try:
                await state["sentences"].check(request.sentence, num_vehicles)
            except Refused as err:
                raise ApiError(422, str(err), refused=True, suggestions=err.suggestions) from None
        try:
            job = jobs.submit(spec, request.scene)
        except QueueFull as err:
            raise ApiError(429, str(err)) from None
        return jobs.status(job.id)

    def _checked(request: RunRequest, voc: Vocabulary) -> tuple[RunSpec, int]:
        """The run ``request`` asks for, checked (scene, duration, policy, language model, exports),
        and the number of vehicles at its start."""
        try:
            scene_set, entry = scenes.lookup(request.scene)
            view = scenes.view(request.scene, request.duration_s)
        except KeyError as err:
            raise ApiError(404, str(err.args[0])) from None
        except ValueError as err:
            raise ApiError(422, str(err)) from None
        if request.policy not in voc.policies:
            raise ApiError(422, f"unknown policy {request.policy!r}; known: {', '.join(voc.policies)}")
        if request.llm and config.llm is None:
            raise ApiError(422, "no language model is configured on this server")
        for kind in request.exports:
            try:
                check_export_kind(kind)  # commonroad-io missing: said before the run
            except ValueError as err:
                raise ApiError(422, str(err)) from None
        return RunSpec(
            serial=0, out_dir="", scene_id=entry.id,
            data=None if scene_set.data is None else str(scene_set.data),
            sentence=request.sentence, seed=request.seed, duration_s=request.duration_s,
            policy=request.policy, guards="on" if request.guards else "off", llm=request.llm,
            compare=request.compare, exports=tuple(dict.fromkeys(request.exports)),
        ), int(view["vehicles"])

    @app.get("/api/runs")
    async def run_list() -> list[dict[str, Any]]:
        return jobs.listing()

    @app.get("/api/runs/{job_id}")
    async def run_status(job_id: str) -> dict[str, Any]:
        return jobs.status(_job_id(job_id))

    @app.post("/api/runs/{job_id}/cancel")
    async def cancel(job_id: str) -> dict[str, Any]:
        return jobs.cancel(_job_id(job_id))

    @app.get("/api/runs/{job_id}/frames")
    async def run_frames(job_id: str, since: int = Query(0, ge=0)) -> dict[str, Any]:
        return jobs.frames(_job_id(job_id), since)

    @app.get("/api/runs/{job_id}/playback")
    async def run_playback(job_id: str) -> FileResponse:
        job = jobs.get(_job_id(job_id))
        if job.rollout_at is None or "playback.json" not in job.files:
            raise ApiError(404, "the run has no rollout yet")
        return FileResponse(job.out_dir / "playback.json", media_type="application/json")

    @app.get("/api/runs/{job_id}/files/{name}")
    async def run_file(job_id: str, name: str) -> FileResponse:
        job = jobs.get(_job_id(job_id))
        if not FILE_NAME.match(name) or name not in job.files:
            raise ApiError(404, f"the run has no file {name[:64]!r}")
        return FileResponse(job.out_dir / name, filename=f"{job.spec.scene_id}-{job.id}-{name}")

    def _job_id(text: str) -> str:
        if not JOB_ID.match(text) or text not in jobs.jobs:
            raise ApiError(404, f"no run {text[:20]!r}")
        return text

    return app
