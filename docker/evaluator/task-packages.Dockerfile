# An evaluator image with an organizer's task packages added (docs/task-packages.md): FROM the
# project's evaluator image, pinned by digest, with the packages installed into its virtualenv
# under the pins the evaluator was built with. The build context is the task package's own
# directory (its pyproject.toml or setup.py beside its code):
#
#   docker build -f /path/to/manieval/docker/evaluator/task-packages.Dockerfile \
#       --build-arg EVALUATOR=registry.example.org/manieval/evaluator@sha256:<digest> \
#       -t registry.example.org/lab/evaluator-lab-tasks:0.1.0 path/to/my_lab_tasks
#
# Then push it, resolve its digest, list it pinned by digest in the workers'
# MANIEVAL_EVALUATOR_IMAGES and load the challenge with `--evaluator-image` (docs/deploy.md,
# "Task packages"). A package that is no distribution (a directory with an
# __init__.py) goes under /app instead, which is on PYTHONPATH: `COPY my_lab_tasks
# /app/my_lab_tasks` in place of the install below.
#
# No default: the evaluator to build on is the one the service runs, by digest, never a tag.
ARG EVALUATOR

FROM ${EVALUATOR}
USER 0:0
COPY . /tmp/task-package
# -c constraints.txt: the evaluator's own pins (ManiSkill, SAPIEN, torch, numpy) hold; pip
# refuses a package that asks for other versions rather than change what the scores depend on.
# Compiled now: the root filesystem is read-only when the image runs.
RUN set -eu; \
    cd /app; \
    /opt/venv/bin/pip install --no-cache-dir -c constraints.txt /tmp/task-package; \
    rm -rf /tmp/task-package; \
    /opt/venv/bin/python -m compileall -q /opt/venv/lib
USER 10001:10000
CMD ["manieval", "evaluate-job"]
