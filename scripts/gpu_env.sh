# Sourced on a GPU machine that has PyTorch but no project install and no network (e.g. a lent cloud
# GPU): installs the wheels in .whl/ (diffusers and what it needs beyond the machine's packages) under
# /tmp/site and puts the package from this checkout on PYTHONPATH. Set TTS_GIT_SHA to the commit sent:
# results record it as their git SHA (the copy's own .git may be missing or stale).
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site
fi
rm -rf /tmp/pkg && mkdir -p /tmp/pkg && cp -r tts /tmp/pkg/tts && cp -r adapters /tmp/pkg/tts/adapters
export PYTHONPATH=/tmp/pkg${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
python3 -P -c "import torch, diffusers, tts.adapters; print('torch', torch.__version__, torch.cuda.get_device_name(0))"
