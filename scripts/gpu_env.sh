# Sourced on a GPU machine that has PyTorch but no project install and no network (e.g. an offline cloud
# GPU): installs the wheels in .whl/ (diffusers and what it needs beyond the machine's packages) under
# build/gpu/site and puts the package from this checkout (as build/gpu/pkg/tts) on PYTHONPATH. Set
# TTS_GIT_SHA to the commit sent: results record it as their git SHA (the copy's own .git may be
# missing or stale). Let the tools write their results where they do by default (under results/)
# and copy them out afterwards, so that their recorded command holds no machine's path.
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target build/gpu/site \
    .whl/*.whl && export PYTHONPATH="$PWD/build/gpu/site"
fi
rm -rf build/gpu/pkg && mkdir -p build/gpu/pkg && cp -r tts build/gpu/pkg/tts && cp -r adapters build/gpu/pkg/tts/adapters
export PYTHONPATH="$PWD/build/gpu/pkg${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
python3 -P -c "import torch, diffusers, tts.adapters; print('torch', torch.__version__, torch.cuda.get_device_name(0))"
