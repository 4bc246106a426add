"""The committed web bundle (orchestration/service/web/app.js) is built from the sources beside it: its
banner names the SHA-256 of web/src/ and package-lock.json that scripts/build_web.sh hashed, and this
recomputes it without npm. A mismatch means src/ or the lock changed and app.js was not rebuilt."""

from __future__ import annotations

import hashlib
import re
import shutil
from pathlib import Path

WEB = Path(__file__).resolve().parents[1] / "orchestration" / "service" / "web"
BANNER = re.compile(
    r"^/\*! rllock web page: built by scripts/build_web\.sh .* sources sha256:([0-9a-f]{64});"
)


def sources_sha256(web: Path) -> str:
    """What build_web.sh hashes: each file under src/ (sorted by path), then package-lock.json, as its
    path, a NUL, its length in bytes, a NUL, and its bytes."""
    paths = sorted(p.relative_to(web).as_posix() for p in (web / "src").rglob("*") if p.is_file())
    digest = hashlib.sha256()
    for name in [*paths, "package-lock.json"]:
        data = (web / name).read_bytes()
        digest.update(f"{name}\0{len(data)}\0".encode() + data)
    return digest.hexdigest()


def test_app_js_is_built_from_the_sources_beside_it():
    with (WEB / "app.js").open() as bundle:
        first = bundle.readline()
    found = BANNER.match(first)
    assert found, f"app.js has no build banner: rebuild it with scripts/build_web.sh ({first[:80]!r})"
    assert found.group(1) == sources_sha256(WEB), (
        "orchestration/service/web/src or package-lock.json changed since app.js was built: "
        "run scripts/build_web.sh and commit app.js"
    )


def test_the_hash_sees_every_source_and_its_path(tmp_path):
    shutil.copytree(WEB / "src", tmp_path / "src")
    shutil.copy(WEB / "package-lock.json", tmp_path)
    before = sources_sha256(tmp_path)
    main = tmp_path / "src" / "main.js"
    main.write_text(main.read_text() + "\n")
    edited = sources_sha256(tmp_path)
    main.rename(tmp_path / "src" / "other.js")
    renamed = sources_sha256(tmp_path)
    (tmp_path / "src" / "extra.js").write_text("")
    assert len({before, edited, renamed, sources_sha256(tmp_path)}) == 4
