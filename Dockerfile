# Builds hmdrt and runs the README's two commands: the test suite at build time, the main job as
# the container's command (its run report lands in /home/hmdrt/out).
FROM python:3.11-slim

RUN useradd --create-home hmdrt
USER hmdrt
WORKDIR /home/hmdrt/app
ENV PATH=/home/hmdrt/.local/bin:$PATH \
    PIP_NO_CACHE_DIR=1

COPY --chown=hmdrt:hmdrt . .
RUN pip install --user -e '.[test]' && pytest -q

VOLUME /home/hmdrt/out
CMD ["hmdrt", "run", "configs/default.toml", "--duration", "10", "--report", "/home/hmdrt/out/report.json"]
