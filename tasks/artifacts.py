"""Per-scene Prefect artifact: the scene's counts and figures, shown in the UI.

The figures are inlined as base64 ``data:`` URIs in a markdown artifact, so the UI shows
them with no file server and no network (Prefect renders images in markdown artifacts).
Best effort: outside a run, or when the API refuses, nothing happens.
"""

from __future__ import annotations

import base64
import re

from freescale_core.store.store import Store

FIGURES_IN_ARTIFACT = ("funnel.png", "cameras.png", "scores.png", "certainty.png",
                       "contact_sheet.png")


def scene_markdown(store: Store, scene_id: str, inline: bool = True) -> str:
    """Markdown of one scene: status, counts, seconds and (inlined) figures."""
    st = store.read_status(scene_id)
    counts, secs, info = st.get("counts", {}), st.get("seconds", {}), st.get("info", {})
    md = [f"# {scene_id}: {st.get('status')}", ""]
    if st.get("error"):
        md += [f"**error**: `{st['error'][:500]}`", ""]
    rows = [("training views", counts.get("n_images")), ("Gaussians", counts.get("n_gaussians")),
            ("candidates", counts.get("n_candidates")), ("NMS-selected", counts.get("n_selected")),
            ("free views", counts.get("n_free_views")), ("scarce (< target)", info.get("scarce")),
            ("train PSNR (dB)", info.get("recon_train_psnr")),
            ("test PSNR (dB)", info.get("recon_test_psnr"))]
    md += ["| quantity | value |", "|---|---|"]
    for k, v in rows:
        if v is not None:
            md.append(f"| {k} | {f'{v:.2f}' if isinstance(v, float) else v} |")
    if secs:
        md.append("| seconds | " + ", ".join(f"{k} {v:.1f}" for k, v in secs.items()) + " |")
    md.append("")
    d = store.current_version_dir(scene_id)
    if d is not None:
        for name in FIGURES_IN_ARTIFACT:
            p = d / name
            if not p.is_file():
                continue
            title = name[:-4].replace("_", " ")
            if inline:
                mime, data = _compact(p)
                b64 = base64.b64encode(data).decode()
                md += [f"## {title}", "", f"![{title}](data:{mime};base64,{b64})", ""]
            else:
                md += [f"## {title}", "", f"`{p}`", ""]
    return "\n".join(md)


def _compact(p, max_width: int = 1000) -> tuple[str, bytes]:
    """A figure small enough for an artifact (the API refuses events over ~1.5 MB): the PNG
    as is when small, else a JPEG at most ``max_width`` wide."""
    data = p.read_bytes()
    if len(data) <= 150_000:
        return "image/png", data
    import io

    from PIL import Image

    im = Image.open(io.BytesIO(data)).convert("RGB")
    if im.width > max_width:
        im = im.resize((max_width, round(im.height * max_width / im.width)), Image.LANCZOS)
    buf = io.BytesIO()
    im.save(buf, format="JPEG", quality=80, optimize=True)
    return "image/jpeg", buf.getvalue()


def publish_scene_artifact(store: Store, scene_id: str) -> None:
    try:
        from prefect.artifacts import create_markdown_artifact
        from prefect.context import TaskRunContext

        if TaskRunContext.get() is None:
            return
        key = re.sub(r"[^a-z0-9-]+", "-", f"scene-{scene_id}".lower()).strip("-")[:100]
        create_markdown_artifact(markdown=scene_markdown(store, scene_id), key=key,
                                 description=f"FreeScale scene {scene_id}: counts and figures")
    except Exception as e:  # noqa: BLE001 - artifacts are a convenience
        from tasks.progress import run_logger

        run_logger().warning("could not create the artifact of scene %s: %s", scene_id, e)
