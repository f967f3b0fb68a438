# The offline path, first build: the pinned dependencies on a base made from Debian
# packages, without any registry or index (see deploy/README.md; `./dev compose up` runs
# it through deploy/stack.py when no registry answers). The base image:
#   debootstrap --variant=minbase --include=python3,python3-venv bookworm DIR
#   tar -C DIR -c . | podman import - semservo-base:bookworm-KEY
# The context is a wheelhouse built on the host (pip download of pyproject.toml's pins,
# requirements.txt beside the wheels). Tagged semservo-deps:KEY, KEY from the pins and
# the base: built again only when they change. deploy/offline.Dockerfile adds the project.
ARG BASE=semservo-base:bookworm
FROM ${BASE}
ENV PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PATH=/opt/semservo/bin:$PATH \
    SEMSERVO_BIND_HOST=0.0.0.0 \
    NUMBA_CACHE_DIR=/home/semservo/.cache/numba \
    LANG=C.UTF-8
# Unprivileged at run time, as deploy/Dockerfile: uid 1000 reads the keys at /keys and
# writes the records volume at /data/runs; dialout for a real serial device; its home
# keeps the compiled kernels (numba) and FFTW wisdom.
RUN useradd --system --uid 1000 --groups dialout --create-home --home-dir /home/semservo semservo \
    && mkdir -p /data/runs && chown semservo:semservo /data/runs \
    && python3 -m venv /opt/semservo
# The wheelhouse is mounted for this step only: the wheels do not stay in a layer.
RUN --mount=type=bind,target=/tmp/wheelhouse \
    pip install --no-index --find-links /tmp/wheelhouse -r /tmp/wheelhouse/requirements.txt
USER semservo
WORKDIR /data
ENTRYPOINT []
CMD ["semservo", "--help"]
