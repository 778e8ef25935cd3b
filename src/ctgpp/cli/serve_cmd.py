"""``ctgpp serve``: the playground in the browser (:mod:`ctgpp.serve`) on a local HTTP server.

The web stack (FastAPI, uvicorn) is the optional ``serve`` extra, imported only when the command runs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ctgpp.cli.common import add_llm_args, llm_config

SERVE_EXTRA = "ctgpp serve needs the web server packages: pip install 'ctgpp[serve]'"


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="the playground in the browser: pick a scene, type a sentence, watch")
    p.add_argument("--port", type=int, default=8000, help="TCP port")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0 opens it to the network)",
    )
    p.add_argument(
        "--data",
        type=Path,
        action="append",
        default=[],
        metavar="DIR",
        help="a directory of converted scenes to offer beside the embedded ones (repeatable; default: none)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("ctgpp-serve"),
        metavar="DIR",
        help="where each run's folder is written (rollout table, metrics.json, exports)",
    )
    p.add_argument("--workers", type=int, default=1, help="simulation processes (runs at once)")
    add_llm_args(p)
    p.set_defaults(run=run_serve)


def run_serve(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise ValueError(f"--port {args.port} is not a TCP port (1-65535)")
    if args.workers < 1:
        raise ValueError("--workers must be at least 1")
    for path in args.data:
        if not Path(path).is_dir():
            raise FileNotFoundError(f"--data {path}: not a directory")
    try:
        import uvicorn

        from ctgpp.serve.app import ServeConfig, create_app
    except ImportError as err:
        raise ValueError(f"{SERVE_EXTRA} ({err.name} is missing)") from None
    llm = None
    if args.llm_model or os.environ.get("CTGPP_LLM_MODEL"):  # resolving imports torch: only when named
        from ctgpp.language.llm.client import LLMError

        try:
            llm = llm_config(args)
        except LLMError as err:
            raise ValueError(str(err)) from None
    config = ServeConfig(data=tuple(args.data), out=args.out, llm=llm, workers=args.workers)
    app = create_app(config)
    model = f", language model {llm.model}" if llm is not None else ""
    url = f"http://{_url_host(args.host)}:{args.port}/"
    print(f"ctgpp serve: {url}  (runs in {args.out}{model}; Ctrl+C stops)", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host
