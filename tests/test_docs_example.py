"""The documentation's code runs as written.

Every ```python block in docs/*.md is executed by ``test_doc_block``, each in a fresh namespace and
in a temporary working directory, unless it is marked not-runnable: an HTML comment starting with
``<!-- not-run`` (a reason may follow, ``<!-- not-run: needs your checkpoint -->``) on the line
right before the opening fence (blank lines in between are allowed). Mark only blocks that need a
user's checkpoint, dataset, simulator or GPU; every other block builds its own small model (an
nn.TransformerEncoder, a tiny DiT or DP-T) and must run in a second or two on CPU. A block that needs
an optional extra which is not installed (diffusers, timm, robosuite, ...) is skipped, not failed.

``test_custom_block_example`` also checks what docs/custom_blocks.md promises about its example:
dense outputs bit-identical, the branch names, the exact budget, real MAC savings.
"""
import re
from pathlib import Path

import pytest
import torch
import torch.nn as nn

import tts

DOCS = Path(__file__).resolve().parents[1] / "docs"
NOT_RUN = "<!-- not-run"
OPTIONAL = {"diffusers", "timm", "torchvision", "robosuite", "mujoco", "h5py", "matplotlib", "accelerate", "scipy",
            "sklearn", "pytorch_fid"}
_FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.S | re.M)

pytestmark = pytest.mark.usefixtures("one_thread")  # small models: one thread is fastest on a shared CPU


def doc_blocks(path: Path) -> list[tuple[int, str, bool]]:
    """(line number, code, runnable) of every ```python block of ``path``."""
    text = path.read_text()
    out = []
    for m in _FENCE.finditer(text):
        before = text[: m.start()].rstrip().splitlines()
        marked = bool(before) and before[-1].strip().startswith(NOT_RUN)
        out.append((text.count("\n", 0, m.start()) + 1, m.group(1), not marked))
    return out


def _runnable():
    for page in sorted(DOCS.glob("*.md")):
        for line, code, runnable in doc_blocks(page):
            if runnable:
                yield pytest.param(page, line, code, id=f"{page.name}:{line}")


RUNNABLE = list(_runnable())


def test_docs_have_runnable_blocks():
    pages = {p.values[0].name for p in RUNNABLE}
    assert {"quickstart.md", "concepts.md", "custom_blocks.md", "plans_and_baselines.md"} <= pages, pages


@pytest.mark.parametrize("page,line,code", RUNNABLE)
def test_doc_block(page, line, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {"__name__": f"docs_{page.stem}_{line}"}
    try:
        exec(compile(code, f"{page.name}:{line}", "exec"), ns)
    except ModuleNotFoundError as e:
        if (e.name or "").split(".")[0] in OPTIONAL:
            pytest.skip(f"{page.name}:{line} needs the optional package {e.name}")
        raise


def test_index_links_every_page_and_figure():
    index = (DOCS / "README.md").read_text()
    wanted = [p.name for p in DOCS.glob("*.md") if p.name != "README.md"] + [p.name for p in DOCS.glob("*.png")]
    wanted += ["results/robot.md", "results/image.md"]
    missing = [w for w in wanted if f"]({w})" not in index]
    assert not missing, f"docs/README.md does not link {missing}"


def _anchor(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_links_between_pages_resolve():
    """Relative links in docs/*.md point at existing files and headings (docs/results/ is generated
    by eval/tables.py: its pages are only checked once they exist)."""
    bad = []
    for page in sorted(DOCS.glob("*.md")):
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+://", target):
                continue
            path, _, anchor = target.partition("#")
            file = DOCS / path if path else page
            if not file.exists():
                if not path.startswith("results/"):
                    bad.append(f"{page.name}: {target} (no such file)")
                continue
            if anchor and file.suffix == ".md":
                headings = re.findall(r"^#+ (.+)$", file.read_text(), re.M)
                if anchor not in {_anchor(h) for h in headings}:
                    bad.append(f"{page.name}: {target} (no such heading)")
    assert not bad, bad


# ------------------------------------------------------------------------------------ custom blocks
def _custom_block_namespace():
    code = next(c for _, c, run in doc_blocks(DOCS / "custom_blocks.md") if run and "class MyBlock" in c)
    ns: dict = {"__name__": "docs_custom_blocks"}
    exec(code, ns)
    return ns


class Net(nn.Module):
    def __init__(self, block_cls, d=16, n=3):
        super().__init__()
        self.blocks = nn.ModuleList(block_cls(d) for _ in range(n))

    def forward(self, x, t, cond):
        for b in self.blocks:
            x = b(x, cond)
        return x


def test_custom_block_example():
    ns = _custom_block_namespace()
    model = Net(ns["MyBlock"]).eval()
    x, cond = torch.randn(2, 5, 16), torch.randn(2, 5, 16)
    with torch.no_grad():
        ref = model(x, torch.tensor(3), cond)
    with tts.accelerate(model, ("forward", "timestep"), blocks={"blocks.*": ns["spec"]}, fast_dense=False) as acc:
        with torch.no_grad():
            assert torch.equal(model(x, torch.tensor(3), cond), ref)
        assert acc.branch_names == [f"blocks.{i}.{n}" for i in range(3) for n in ("attn", "mlp")]
    with tts.accelerate(model, ("forward", "timestep"), blocks={"blocks.*": ns["spec"]}, sparsity=0.8) as acc:
        with torch.no_grad():
            for k in range(10):
                model(x, torch.tensor(10 - k), cond)
        assert acc.summary().sparsity() == 0.8
        dense, realised = acc.summary().macs(acc.summary().calls[-1])
        assert realised < 0.3 * dense
