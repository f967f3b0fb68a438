# The offline path, second build: the project's own wheel on the dependencies image
# (deploy/offline-deps.Dockerfile). The context is a folder holding the wheel. Nothing
# is fetched: --no-index, and pip checks that the installed pins satisfy the project.
ARG DEPS=semservo-deps:latest
FROM ${DEPS}
USER root
COPY semservo-*.whl /tmp/
RUN pip install --no-index /tmp/semservo-*.whl && rm /tmp/semservo-*.whl
USER semservo
