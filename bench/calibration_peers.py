#!/usr/bin/python3
"""holocap calibrate beside mrcal's own tool and OpenCV on the same images (Debian's python3:
mrcal, cv2, numpy).

  calibration_peers.py run --holocap BIN --take TAKE --work DIR [--lensmodel M] [--focal F]
                           [--splined M]
      TAKE is a simulated board take of a square chessboard (its gt/ scores, nothing else).
      Every solver runs on the PNGs of `holocap export images --format png` (written into
      DIR/images), each with its own corners and again with holocap's (`calibrate
      --write-corners`), and is scored against the truth: one table on stdout.
  calibration_peers.py real --holocap BIN --data DIR --work DIR [--focal F]
      Real photographs, no truth: DIR holds left*.jpg, right*.jpg (paired by number) and
      board.yaml (a chessboard). `holocap import images` makes the take, and holocap, mrcal
      (on holocap's corners; mrgingham reads square N x N grids only and is left out of a board
      with unequal sides, with that reason) and OpenCV (its own corners and holocap's) solve it;
      the table gives each one's fx fy cx cy per camera, the second camera's baseline and
      rotation, RMS, outliers, holocap's cross-validation and CPU seconds, beside holocap's own
      1-sigma of each figure, and how far holocap's corners lie from OpenCV's cornerSubPix.
  calibration_peers.py check-corners --holocap BIN [--work DIR]
      The bench's corner files checked on a tiny simulated take: holocap's corners.vnl read
      back lie on the true corners (each frame set numbered alike in every camera, up to a turn
      of the board), and written again they read back the same. Exit 77 (skipped) without
      mrcal or cv2.

The solvers, each timed in CPU seconds (children's and its own):
  holocap   `holocap calibrate --no-pictures --lens-model M` (its finder; then --detector
            mrgingham: holocap's solve on mrgingham's corners)
  mrcal     mrgingham, then mrcal-calibrate-cameras --corners-cache (mrcal's recommended path);
            again on holocap's corners.vnl; with --splined, mrgingham's corners in the splined
            model mrcal recommends
  opencv    findChessboardCorners + cornerSubPix per image, calibrateCamera per camera (the
            standard 5-coefficient model, which is mrcal's LENSMODEL_OPENCV5), then
            stereoCalibrate (CALIB_FIX_INTRINSIC) of each camera against the first; again on
            holocap's corners. A square board can be numbered from either end in two cameras:
            before stereoCalibrate each view of a frame set is turned to the numbering whose
            relative pose agrees with the most frame sets (as holocap does), else left out.
Scores: rms (per coordinate, px, inliers of the solver's own fit: OpenCV keeps every point),
focal (worst |f - f_true| / f_true, %), pp (worst principal point error, px), rot/trans (worst
camera pose relative to the first camera against the truth's, degrees and mm of its centre),
proj (a 16 x 12 grid of pixels of every camera unprojected by the truth to 2 m, carried into the
first camera's frame by the truth and projected by the solved rig: mean and max px; own: the
same in the camera's own frame, its intrinsics alone).
"""
import argparse
import glob
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time

try:
    import cv2
    import mrcal
    import numpy as np
except ImportError as e:  # the test's skip
    print(f"calibration_peers.py: skipped: /usr/bin/python3 lacks {e.name} "
          "(Debian python3-mrcal, python3-opencv)")
    sys.exit(77)

GRID = (16, 12)      # projection grid per camera
DISTANCE_M = 2.0     # working distance of the projection figures
TURN_LIMIT_DEG = 2.0  # a view's relative pose must agree this well with the frame sets' consensus


# ----------------------------------------------------------------------------------------------
# corners.vnl: "# filename x y level", per image its points in grid order, "- - -" unseen.

def read_vnl(path):
    """Returns [(filename, array N x 3 of x, y, weight)] in file order; weight 1 / 2^level, -1
    where the point was not seen."""
    views, current, rows = [], None, []
    with open(path, encoding="ascii") as f:
        for line in f:
            if line.startswith("#") or not line.strip():
                continue
            fields = line.split()
            if len(fields) not in (3, 4):
                raise ValueError(f"{path}: not a corners.vnl row: {line!r}")
            if fields[0] != current:
                if current is not None:
                    views.append((current, np.array(rows)))
                current, rows = fields[0], []
            if fields[1] == "-" or fields[2] == "-" or (len(fields) == 4 and fields[3] == "-"):
                rows.append((-1.0, -1.0, -1.0))
            else:
                level = float(fields[3]) if len(fields) == 4 else 0.0
                rows.append((float(fields[1]), float(fields[2]), 0.5 ** level))
    if current is not None:
        views.append((current, np.array(rows)))
    return views


def write_vnl(path, views):
    """Writes [(filename, N x 3)] as read_vnl reads it (weights 1 / 2^level)."""
    with open(path, "w", encoding="ascii") as f:
        f.write("# filename x y level\n")
        for name, points in views:
            for x, y, w in points:
                if w > 0:
                    f.write(f"{name} {x:.6f} {y:.6f} {round(-np.log2(w)):d}\n")
                else:
                    f.write(f"{name} - - -\n")


def view_key(name):
    """'left/000012.png' -> ('left', 12): the camera folder and the frame set."""
    m = re.match(r"(.*)/(\d+)\.\w+$", name)
    if m is None:
        raise ValueError(f"image name {name!r} is not CAMERA/NNNNNN.EXT")
    return os.path.basename(m.group(1)), int(m.group(2))


# ----------------------------------------------------------------------------------------------
# The take.

class Take:
    def __init__(self, path):
        self.path = path
        with open(os.path.join(path, "take.json")) as f:
            take = json.load(f)
        self.cameras = [s["name"] for s in take["rig"]["sensors"] if s.get("role") == "color"]
        with open(os.path.join(path, "gt", "board.json")) as f:
            board = json.load(f)
        layout = board["layout"]
        self.width_n, self.height_n = layout["width_n"], layout["height_n"]
        self.spacing = layout["spacing"]
        self.world_from_board = {b["set"]: np.array(b["matrix"]) for b in board["world_from_board"]}
        self.truth = {c: mrcal.cameramodel(os.path.join(path, "gt", "cameras", c + ".cameramodel"))
                      for c in self.cameras}

    def imagersize(self):
        return tuple(int(v) for v in self.truth[self.cameras[0]].imagersize())

    def object_points(self):
        """The board's grid (z = 0) in grid order, j * width_n + i: mrcal's and holocap's."""
        j, i = np.mgrid[0:self.height_n, 0:self.width_n]
        return np.stack([i.ravel() * self.spacing, j.ravel() * self.spacing,
                         np.zeros(i.size)], axis=1)

    def true_corners(self, camera, frame_set):
        """The true pixel of every grid point in one view (mrcal's projection of the truth)."""
        m = self.truth[camera]
        world = (self.world_from_board[frame_set][:3, :3] @ self.object_points().T).T + \
            self.world_from_board[frame_set][:3, 3]
        cam = mrcal.transform_point_rt(m.extrinsics_rt_fromref(), world)
        return mrcal.project(cam, *m.intrinsics())


def turn_orders(width_n, height_n):
    """Grid-index orders of the board's turns that leave a width_n x height_n grid a grid: the
    identity and 180 degrees, and 90 and 270 on a square grid. turned[r] = points[order[r]]."""
    j, i = np.mgrid[0:height_n, 0:width_n]
    i, j = i.ravel(), j.ravel()
    orders = [j * width_n + i, (height_n - 1 - j) * width_n + (width_n - 1 - i)]
    if width_n == height_n:
        orders += [(width_n - 1 - i) * width_n + j, i * width_n + (width_n - 1 - j)]
    return orders


def check_corners(take, vnl_path, work):
    """Holocap's corners against the truth and through the writer; returns the failures."""
    failures = []
    views = read_vnl(vnl_path)
    orders = turn_orders(take.width_n, take.height_n)
    turn_of_set = {}
    worst = 0.0
    for name, points in views:
        camera, frame_set = view_key(name)
        truth = take.true_corners(camera, frame_set)
        seen = points[:, 2] > 0
        if seen.sum() < 4:
            failures.append(f"{name}: {seen.sum()} points seen")
            continue
        # The turn of the truth's numbering that this view's numbering is.
        errors = [np.abs(points[seen, :2] - truth[order][seen]).max() for order in orders]
        turn = int(np.argmin(errors))
        worst = max(worst, errors[turn])
        if errors[turn] > 0.25:
            failures.append(f"{name}: corners {errors[turn]:.3f} px from the truth's")
        if turn_of_set.setdefault(frame_set, turn) != turn:
            failures.append(f"{name}: numbered turned {turn} where frame set {frame_set}'s other "
                            f"views are turned {turn_of_set[frame_set]}")
    again = os.path.join(work, "again.vnl")
    write_vnl(again, views)
    reread = read_vnl(again)
    if [n for n, _ in reread] != [n for n, _ in views]:
        failures.append("written and read again, the images differ")
    else:
        apart = max(np.abs(a - b).max() for (_, a), (_, b) in zip(views, reread))
        if apart > 1e-6:
            failures.append(f"written and read again, a corner moved {apart:g} px")
    cameras = sorted({view_key(n)[0] for n, _ in views})
    print(f"{len(views)} views of {len(cameras)} cameras ({', '.join(cameras)}), "
          f"{len(turn_of_set)} frame sets; corners within {worst:.3f} px of the truth")
    return failures


# ----------------------------------------------------------------------------------------------
# Timing: CPU seconds of this process and of the children it waited for.

class CpuClock:
    def __init__(self):
        self.start = self.now()

    @staticmethod
    def now():
        c = resource.getrusage(resource.RUSAGE_CHILDREN)
        return time.process_time() + c.ru_utime + c.ru_stime

    def seconds(self):
        return self.now() - self.start


def run(command, cwd=None, log=None):
    out = subprocess.run(command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, check=False)
    if log is not None:
        with open(log, "w") as f:
            f.write(out.stdout)
    return out.returncode, out.stdout


# ----------------------------------------------------------------------------------------------
# Solvers. Each returns a dict: models (camera -> mrcal.cameramodel, extrinsics from the first
# camera), rms, views, cpu, note.

def models_from_ref(models, cameras):
    """The same models with extrinsics relative to the first camera's frame."""
    ref_from_world = mrcal.invert_rt(models[cameras[0]].extrinsics_rt_fromref())
    out = {}
    for c in cameras:
        m = mrcal.cameramodel(models[c])
        m.extrinsics_rt_fromref(mrcal.compose_rt(models[c].extrinsics_rt_fromref(), ref_from_world))
        out[c] = m
    return out


def holocap_result(take, rc, cpu):
    """What `holocap calibrate` (exit status rc) left in take/calib: a result (cpu, note: the
    ending; models, relative to the first camera, when it trusted the solve) and the report's
    metrics (None when it did not)."""
    with open(os.path.join(take.path, "calib", "report.json")) as f:
        report = json.load(f)
    state = report["summary"]["termination"]
    result = dict(cpu=cpu, note=state if rc == 0 else f"{state} (exit {rc})")
    if rc != 0:
        return result, None
    models = {c: mrcal.cameramodel(os.path.join(take.path, "calib", c + ".cameramodel"))
              for c in take.cameras}
    result["models"] = models_from_ref(models, take.cameras)
    return result, report["metrics"]


def solve_holocap(args, take, work, detector):
    clock = CpuClock()
    command = [args.holocap, "calibrate", take.path, "--no-pictures", "--lens-model",
               args.lensmodel, "--detector", detector]
    if detector == "holocap":
        command += ["--write-corners", os.path.join(work, "images", "holocap.vnl")]
    rc, _ = run(command, log=os.path.join(work, f"holocap-{detector}.log"))
    result, metrics = holocap_result(take, rc, clock.seconds())
    if metrics is None:
        return result
    # The solve's own 1-sigma of the principal point, the worst camera's: how far apart two
    # solves of the same views may honestly land.
    pp_sigma = max(max(c["intrinsics_sigma"][2:4]) for c in metrics["cameras"].values())
    state = result["note"]
    result.update(rms=metrics["rms_reprojection_px"],
                  views=sum(c["views"] for c in metrics["cameras"].values()),
                  note=f"{state}, principal point 1-sigma {pp_sigma:.3f} px")
    return result


def solve_mrcal(args, take, work, corners, lensmodel, label, extra=()):
    """mrcal-calibrate-cameras on a corners.vnl in work/images (mrgingham's is made first when
    `corners` is 'mrgingham.vnl'; its CPU time counts)."""
    images = os.path.join(work, "images")
    globs = [f"{c}/*.png" for c in take.cameras]
    clock = CpuClock()
    if corners == "mrgingham.vnl" and not os.path.exists(os.path.join(images, corners)):
        rc, out = run(["mrgingham", "--jobs", "1", "--gridn", str(take.width_n)] + globs,
                      cwd=images)
        if rc != 0:
            return dict(cpu=clock.seconds(), note=f"mrgingham exit {rc}")
        with open(os.path.join(images, corners), "w") as f:
            f.write(out)
    outdir = os.path.join(work, f"mrcal-{label}")
    os.makedirs(outdir, exist_ok=True)
    rc, out = run(["mrcal-calibrate-cameras", "--corners-cache", corners, "--lensmodel", lensmodel,
                   "--focal", str(args.focal), "--object-spacing", str(take.spacing),
                   "--object-width-n", str(take.width_n), "--object-height-n", str(take.height_n),
                   "--outdir", outdir] + list(extra) + globs, cwd=images, log=outdir + ".log")
    cpu = clock.seconds()
    if rc != 0:
        return dict(cpu=cpu, note=f"exit {rc}: {out.strip().splitlines()[-1][:60]}")
    files = sorted(glob.glob(os.path.join(outdir, "*.cameramodel")))
    if len(files) != len(take.cameras):
        return dict(cpu=cpu, note=f"{len(files)} models written")
    models = {c: mrcal.cameramodel(f) for c, f in zip(take.cameras, files)}
    inputs = models[take.cameras[0]].optimization_inputs()
    residuals = mrcal.residuals_chessboard(inputs)
    return dict(models=models_from_ref(models, take.cameras), cpu=cpu,
                rms=float(np.sqrt(np.mean(residuals ** 2))),
                views=len(inputs["indices_frame_camintrinsics_camextrinsics"]),
                note=" ".join(extra))


def find_opencv_corners(path, take):
    grey = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    found, corners = cv2.findChessboardCorners(
        grey, (take.width_n, take.height_n),
        cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
    if not found:
        return None
    corners = corners.reshape(-1, 2)
    # OpenCV's common recipe as `calibrate --compare-detectors` runs it: an 11 x 11 half window,
    # shrunk to half the view's smallest corner spacing (a window past the neighbouring corners
    # pulls every corner towards them).
    grid = corners.reshape(take.height_n, take.width_n, 2)
    spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                  np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
    half = int(np.clip(int(0.5 * spacing), 2, 11))
    refined = cv2.cornerSubPix(grey, corners.reshape(-1, 1, 2).astype(np.float32),
                               (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001))
    return np.hstack([refined.reshape(-1, 2).astype(np.float64), np.ones((corners.shape[0], 1))])


def rotation_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def agree_numbering(take, views, K, dist, reference_views, K_ref, dist_ref):
    """Turns each view of a camera (frame set -> N x 3) to the numbering whose pose relative to
    the reference camera's view of its frame set agrees with the most frame sets; views no turn
    brings within TURN_LIMIT_DEG of that consensus are left out. Returns the turned views."""
    obj = take.object_points()

    def pose(points, K, dist):
        seen = points[:, 2] > 0
        ok, rvec, tvec = cv2.solvePnP(obj[seen], points[seen, :2], K, dist)
        return cv2.Rodrigues(rvec)[0] if ok else None

    orders = turn_orders(take.width_n, take.height_n)
    candidates = {}  # frame set -> [relative rotation per turn]
    for s, points in views.items():
        if s not in reference_views:
            continue
        R_ref = pose(reference_views[s], K_ref, dist_ref)
        candidates[s] = [None if R_ref is None else
                         (lambda R: None if R is None else R @ R_ref.T)(pose(points[o], K, dist))
                         for o in orders]
    every = [R for rs in candidates.values() for R in rs if R is not None]
    if not every:
        return {}

    def support(R0):
        return sum(any(R is not None and rotation_deg(R @ R0.T) < TURN_LIMIT_DEG for R in rs)
                   for rs in candidates.values())
    consensus = max(every, key=support)
    turned = {}
    for s, rs in candidates.items():
        apart = [np.inf if R is None else rotation_deg(R @ consensus.T) for R in rs]
        t = int(np.argmin(apart))
        if apart[t] < TURN_LIMIT_DEG:
            turned[s] = views[s][orders[t]]
    return turned


def solve_opencv(take, work, corners_vnl):
    """OpenCV's calibrateCamera per camera and stereoCalibrate against the first camera, on its
    own corners (corners_vnl None) or on a corners.vnl's."""
    clock = CpuClock()
    views = {c: {} for c in take.cameras}  # camera -> frame set -> N x 3
    if corners_vnl is None:
        for c in take.cameras:
            for path in sorted(glob.glob(os.path.join(work, "images", c, "*.png"))):
                found = find_opencv_corners(path, take)
                if found is not None:
                    views[c][view_key(os.path.relpath(path, os.path.join(work, "images")))[1]] = found
    else:
        for name, points in read_vnl(corners_vnl):
            camera, s = view_key(name)
            views[camera][s] = points
    obj = take.object_points().astype(np.float32)
    size = take.imagersize()
    K, dist, sq, n = {}, {}, 0.0, 0
    for c in take.cameras:
        frames = sorted(views[c])
        objs = [obj[views[c][s][:, 2] > 0] for s in frames]
        imgs = [views[c][s][views[c][s][:, 2] > 0, :2].astype(np.float32) for s in frames]
        _, K[c], dist[c], rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, None, None)
        for o, i, r, t in zip(objs, imgs, rvecs, tvecs):
            q = cv2.projectPoints(o, r, t, K[c], dist[c])[0].reshape(-1, 2)
            sq += float(((q - i) ** 2).sum())
            n += 2 * len(o)
    ref = take.cameras[0]
    rt = {ref: np.zeros(6)}
    left_out = 0
    for c in take.cameras[1:]:
        mine = views[c] if corners_vnl else \
            agree_numbering(take, views[c], K[c], dist[c], views[ref], K[ref], dist[ref])
        left_out += len(set(views[c]) & set(views[ref])) - len(set(mine) & set(views[ref]))
        shared = sorted(set(mine) & set(views[ref]))
        objs, img_ref, img_c = [], [], []
        for s in shared:
            both = (views[ref][s][:, 2] > 0) & (mine[s][:, 2] > 0)
            objs.append(obj[both])
            img_ref.append(views[ref][s][both, :2].astype(np.float32))
            img_c.append(mine[s][both, :2].astype(np.float32))
        out = cv2.stereoCalibrate(objs, img_ref, img_c, K[ref], dist[ref], K[c], dist[c], size,
                                  flags=cv2.CALIB_FIX_INTRINSIC)
        R, T = out[5], out[6]
        rt[c] = mrcal.rt_from_Rt(np.vstack([R, T.reshape(1, 3)]))
    cpu = clock.seconds()
    models = {}
    for c in take.cameras:
        intrinsics = np.concatenate([[K[c][0, 0], K[c][1, 1], K[c][0, 2], K[c][1, 2]],
                                     dist[c].ravel()[:5]])
        models[c] = mrcal.cameramodel(intrinsics=("LENSMODEL_OPENCV5", intrinsics),
                                      imagersize=size, extrinsics_rt_fromref=rt[c])
    note = f"{left_out} shared views unturnable" if left_out else ""
    return dict(models=models, cpu=cpu, rms=float(np.sqrt(sq / n)),
                views=sum(len(v) for v in views.values()), note=note)


# ----------------------------------------------------------------------------------------------
# Scores against the truth.

def best_fit(solved, truth, translate):
    """R, t (truth_from_solved) minimising |R solved + t - truth| over the point pairs (Kabsch;
    rotation alone about the origin without `translate`)."""
    cs = solved.mean(axis=0) if translate else np.zeros(3)
    ct = truth.mean(axis=0) if translate else np.zeros(3)
    u, _, vt = np.linalg.svd((solved - cs).T @ (truth - ct))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1, 1, d]) @ u.T
    return R, ct - R @ cs


def score(take, models):
    truth = models_from_ref(take.truth, take.cameras)
    s = dict(focal=0.0, pp=0.0, rot=0.0, trans=0.0)
    splined = False
    grids, truth_points, solved_points = {}, {}, {}
    for c in take.cameras:
        t, m = truth[c], models[c]
        if m.intrinsics()[0].startswith("LENSMODEL_OPENCV"):
            f_t, f_m = t.intrinsics()[1][:2], m.intrinsics()[1][:2]
            s["focal"] = max(s["focal"], 100 * float(np.abs(f_m / f_t - 1).max()))
            s["pp"] = max(s["pp"], float(np.linalg.norm(m.intrinsics()[1][2:4] -
                                                        t.intrinsics()[1][2:4])))
        else:
            splined = True
        Rt_t = mrcal.Rt_from_rt(t.extrinsics_rt_fromref())
        Rt_m = mrcal.Rt_from_rt(m.extrinsics_rt_fromref())
        s["rot"] = max(s["rot"], rotation_deg(Rt_m[:3] @ Rt_t[:3].T))
        s["trans"] = max(s["trans"], 1000 * float(np.linalg.norm(
            Rt_m[:3].T @ Rt_m[3] - Rt_t[:3].T @ Rt_t[3])))
        w, h = t.imagersize()
        u, v = np.meshgrid((np.arange(GRID[0]) + 0.5) * w / GRID[0] - 0.5,
                           (np.arange(GRID[1]) + 0.5) * h / GRID[1] - 0.5)
        grids[c] = np.stack([u.ravel(), v.ravel()], axis=1)
        truth_points[c] = DISTANCE_M * mrcal.unproject(grids[c], *t.intrinsics(), normalize=True)
        solved_points[c] = DISTANCE_M * mrcal.unproject(grids[c], *m.intrinsics(), normalize=True)
    # The rig: the solved first camera's frame laid onto the truth's by the rigid transform that
    # best maps the solved rig's points at 2 m onto the truth's, then every camera's true points
    # projected by the solved rig.
    to_ref = lambda model, p: mrcal.transform_point_rt(
        mrcal.invert_rt(model.extrinsics_rt_fromref()), p)
    R, t_ = best_fit(np.concatenate([to_ref(models[c], solved_points[c]) for c in take.cameras]),
                     np.concatenate([to_ref(truth[c], truth_points[c]) for c in take.cameras]),
                     True)
    rig, own, valid = [], [], []
    for c in take.cameras:
        m = models[c]
        p_solved_ref = (to_ref(truth[c], truth_points[c]) - t_) @ R
        q = mrcal.project(mrcal.transform_point_rt(m.extrinsics_rt_fromref(), p_solved_ref),
                          *m.intrinsics())
        rig.append(np.linalg.norm(q - grids[c], axis=1))
        region = m.valid_intrinsics_region()
        valid.append(np.array([region is not None and cv2.pointPolygonTest(
            region.astype(np.float32), (float(x), float(y)), False) >= 0 for x, y in grids[c]]))
        # Its own frame: the rotation that best lays its solved rays onto the true ones.
        R_own, _ = best_fit(solved_points[c], truth_points[c], False)
        q = mrcal.project(truth_points[c] @ R_own, *m.intrinsics())
        own.append(np.linalg.norm(q - grids[c], axis=1))
    rig, own, valid = np.concatenate(rig), np.concatenate(own), np.concatenate(valid)
    s.update(rig_mean=float(rig.mean()), rig_max=float(rig.max()), own_mean=float(own.mean()),
             own_max=float(own.max()), note="")
    if splined:
        # A splined camera's orientation is not apart from its spline: only the projections
        # compare. Where the views did not reach, a spline extrapolates freely: mrcal's own
        # valid-intrinsics region says where to trust it.
        s["focal"] = s["pp"] = s["rot"] = s["trans"] = None
        if valid.any():
            s["note"] = (f"mrcal's valid region: {100 * valid.mean():.0f}% of the grid, proj "
                         f"{rig[valid].mean():.3f} mean, {rig[valid].max():.3f} max there")
    return s


def print_table(rows):
    head = ("solver", "corners", "model", "views", "rms_px", "focal_%", "pp_px", "rot_deg",
            "trans_mm", "proj_mean", "proj_max", "own_max", "cpu_s")
    print(f"{head[0]:<8} {head[1]:<10} {head[2]:<9} {head[3]:>5} {head[4]:>7} {head[5]:>8} "
          f"{head[6]:>6} {head[7]:>8} {head[8]:>8} {head[9]:>9} {head[10]:>8} {head[11]:>7} "
          f"{head[12]:>6}  note")

    def num(v, spec, width):
        return f"{'-':>{width}}" if v is None else f"{v:>{width}{spec}}"
    for solver, corners, model, r in rows:
        if "models" not in r:
            print(f"{solver:<8} {corners:<10} {model:<9} {'-':>5} " + " ".join(
                f"{'-':>{w}}" for w in (7, 8, 6, 8, 8, 9, 8, 7)) + f" {r['cpu']:>6.1f}  {r['note']}")
            continue
        s = r["score"]
        print(f"{solver:<8} {corners:<10} {model:<9} {r['views']:>5} {r['rms']:>7.4f} "
              f"{num(s['focal'], '.4f', 8)} {num(s['pp'], '.3f', 6)} {num(s['rot'], '.4f', 8)} "
              f"{num(s['trans'], '.3f', 8)} {s['rig_mean']:>9.3f} {s['rig_max']:>8.3f} "
              f"{s['own_max']:>7.3f} {r['cpu']:>6.1f}  {' '.join(filter(None, (r['note'], s['note'])))}")


def main_run(args):
    take = Take(args.take)
    work = os.path.abspath(args.work)
    images = os.path.join(work, "images")
    if os.path.exists(images):
        shutil.rmtree(images)
    rc, out = run([args.holocap, "export", "images", take.path, "--out", images, "--format",
                   "png"])
    if rc != 0:
        sys.exit(f"calibration_peers.py: export images failed: {out}")
    short = args.lensmodel.replace("LENSMODEL_", "")
    rows = [("holocap", "mrgingham", short, solve_holocap(args, take, work, "mrgingham")),
            ("holocap", "holocap", short, solve_holocap(args, take, work, "holocap")),
            ("mrcal", "mrgingham", short,
             solve_mrcal(args, take, work, "mrgingham.vnl", args.lensmodel, "mrgingham")),
            ("mrcal", "holocap", short,
             solve_mrcal(args, take, work, "holocap.vnl", args.lensmodel, "holocap")),
            # Where holocap's solve differs from the tool's: no board warp by default, and
            # mrcal's regularisation (both tools keep it) against OpenCV's none.
            ("mrcal", "mrgingham", short,
             solve_mrcal(args, take, work, "mrgingham.vnl", args.lensmodel, "mrgingham-nowarp",
                         ["--skip-calobject-warp-solve"])),
            ("mrcal", "holocap", short,
             solve_mrcal(args, take, work, "holocap.vnl", args.lensmodel, "holocap-noreg",
                         ["--skip-regularization"])),
            ("opencv", "opencv", "standard", solve_opencv(take, work, None)),
            ("opencv", "holocap", "standard",
             solve_opencv(take, work, os.path.join(images, "holocap.vnl")))]
    if args.splined:
        rows.append(("mrcal", "mrgingham", "splined",
                     solve_mrcal(args, take, work, "mrgingham.vnl", args.splined, "splined")))
    for _, _, _, r in rows:
        if "models" in r:
            r["score"] = score(take, r["models"])
    print_table(rows)


class RealTake:
    """An imported take of photographs: its cameras, the board of a chessboard YAML and the
    images' size (no gt/)."""

    def __init__(self, path, board_yaml, images):
        self.path = path
        with open(os.path.join(path, "take.json")) as f:
            take = json.load(f)
        self.cameras = [s["name"] for s in take["rig"]["sensors"] if s.get("role") == "color"]
        fields = {}
        with open(board_yaml) as f:
            for line in f:
                line = line.split("#", 1)[0]
                if ":" in line:
                    key, value = line.split(":", 1)
                    fields[key.strip()] = value.strip()
        if fields.get("type") != "chessboard":
            sys.exit(f"calibration_peers.py: {board_yaml} is not a chessboard")
        self.width_n = int(fields.get("chessboard_width_n", 9))
        self.height_n = int(fields.get("chessboard_height_n", 6))
        self.spacing = float(fields["spacing"])
        first = sorted(glob.glob(os.path.join(images, self.cameras[0], "*.png")))[0]
        h, w = cv2.imread(first, cv2.IMREAD_GRAYSCALE).shape
        self.size = (w, h)

    def imagersize(self):
        return self.size

    object_points = Take.object_points


def corner_distances(take, images):
    """holocap's corners (holocap.vnl) against OpenCV's findChessboardCorners + cornerSubPix on
    the same images, each view's numbering turned to the closer one: every distance, px."""
    orders = turn_orders(take.width_n, take.height_n)
    distances = []
    for name, points in read_vnl(os.path.join(images, "holocap.vnl")):
        theirs = find_opencv_corners(os.path.join(images, name), take)
        if theirs is None:
            continue
        both = (points[:, 2] > 0)
        best = min((np.linalg.norm(points[both, :2] - theirs[o][both, :2], axis=1)
                    for o in orders), key=lambda d: d.mean())
        distances.append(best)
    return np.concatenate(distances) if distances else np.zeros(0)


def rig_figures(models, cameras):
    """fx fy cx cy per camera, and each further camera's baseline (m) and rotation (degrees)
    relative to the first."""
    out = dict(intrinsics={c: models[c].intrinsics()[1][:4] for c in cameras})
    rt = models[cameras[1]].extrinsics_rt_fromref()
    out["baseline_m"] = float(np.linalg.norm(rt[3:]))
    out["rotation_deg"] = float(np.degrees(np.linalg.norm(rt[:3])))
    return out


def solve_holocap_real(args, take, work, lensmodel, extra=()):
    """holocap calibrate as a user runs it (the board only; `lensmodel` None: its default; then
    `extra`, a tuple of flags), then again with --cross-validate for the halves' agreement."""
    clock = CpuClock()
    command = [args.holocap, "calibrate", take.path, "--no-pictures",
               "--board", args.board] + list(extra)
    if lensmodel:
        command += ["--lens-model", lensmodel]
    elif not extra:
        command += ["--write-corners", os.path.join(work, "images", "holocap.vnl")]
    label = (lensmodel or "default").replace("LENSMODEL_", "") + "".join(extra)
    rc, _ = run(command, log=os.path.join(work, f"holocap-{label}.log"))
    result, metrics = holocap_result(take, rc, clock.seconds())
    if metrics is None:
        return result
    cams = metrics["cameras"]
    second = cams[take.cameras[1]]
    result.update(rms=metrics["rms_reprojection_px"], outliers=metrics["outliers"],
                  views=sum(c["views"] for c in cams.values()),
                  dropped=len(metrics["dropped_views"]) + len(metrics["detection"]["rejected"]),
                  sigma=dict(intrinsics={c: cams[c]["intrinsics_sigma"][:4] for c in take.cameras},
                             baseline_m=second["center_sigma_mm"] / 1000,
                             rotation_deg=second["rotation_sigma_deg"]))
    if metrics.get("board_warp_m") is not None:
        result["note"] = " ".join(extra + (result["note"],)) + \
            ", board warp {:.3f} {:.3f} mm".format(*(1000 * w for w in metrics["board_warp_m"]))
    shutil.copytree(os.path.join(take.path, "calib"), os.path.join(work, f"calib-{label}"),
                    dirs_exist_ok=True)
    # The cross-validation: two disjoint halves of the frame sets against the prediction.
    command = [c for c in command if not c.endswith("holocap.vnl") and c != "--write-corners"]
    rc_cv, _ = run(command + ["--cross-validate"], log=os.path.join(work, f"holocap-{label}-cv.log"))
    cv_path = os.path.join(take.path, "calib",
                           "report.json" if rc_cv == 0 else "report.failed.json")
    with open(cv_path) as f:
        cv_report = json.load(f)
    cv = cv_report["metrics"].get("cross_validation", {})
    result["cross_validation"] = (
        f"cross-validated: {cv_report['summary']['termination']}, the halves "
        f"{cv.get('worst_ratio_to_predicted', 0):.1f}x their predicted difference (limit 2x)")
    return result


def solve_mrcal_real(args, take, work, lensmodel, label, extra=()):
    r = solve_mrcal(args, take, work, "holocap.vnl", lensmodel, label, extra)
    if "models" in r:
        files = sorted(glob.glob(os.path.join(work, f"mrcal-{label}", "*.cameramodel")))
        inputs = mrcal.cameramodel(files[0]).optimization_inputs()
        r["outliers"] = int((inputs["observations_board"][..., 2] <= 0).sum())
        if "--skip-calobject-warp-solve" not in extra:
            r["note"] = "; ".join(filter(None, (r["note"], "board warp {:.3f} {:.3f} mm".format(
                *(1000 * w for w in inputs["calobject_warp"])))))
    return r


def print_real_table(rows, cameras, sigma):
    head = f"{'solver':<8} {'corners':<9} {'model':<8} {'views':>5} {'rms_px':>6} {'outl':>4}"
    for c in cameras:
        head += f" {c + '_fx':>9} {c + '_fy':>9} {c + '_cx':>9} {c + '_cy':>9}"
    head += f" {'base_mm':>8} {'rot_deg':>7} {'cpu_s':>6}  note"
    print(head)

    def line(solver, corners, model, r):
        if "models" not in r:
            return f"{solver:<8} {corners:<9} {model:<8} {'-':>5} {'-':>6} {'-':>4}" + \
                " ".join(f"{'-':>9}" for _ in range(4 * len(cameras))) + \
                f" {'-':>8} {'-':>7} {r['cpu']:>6.1f}  {r['note']}"
        f = rig_figures(r["models"], cameras)
        text = f"{solver:<8} {corners:<9} {model:<8} {r['views']:>5} {r['rms']:>6.3f} " \
            f"{r.get('outliers', 0):>4}"
        for c in cameras:
            text += "".join(f" {v:>9.2f}" for v in f["intrinsics"][c])
        note = "; ".join(filter(None, (r["note"], r.get("cross_validation", ""))))
        return text + f" {1000 * f['baseline_m']:>8.2f} {f['rotation_deg']:>7.3f} " \
            f"{r['cpu']:>6.1f}  {note}"
    for row in rows:
        print(line(*row))
    text = f"{'holocap':<8} {'1-sigma':<9} {'OPENCV5':<8} {'':>5} {'':>6} {'':>4}"
    for c in cameras:
        text += "".join(f" {v:>9.2f}" for v in sigma["intrinsics"][c])
    print(text + f" {1000 * sigma['baseline_m']:>8.2f} {sigma['rotation_deg']:>7.3f}")


def main_real(args):
    work = os.path.abspath(args.work)
    os.makedirs(work, exist_ok=True)
    take_dir = os.path.join(work, "take")
    args.board = os.path.join(args.data, "board.yaml")
    rc, out = run([args.holocap, "import", "images", "--camera",
                   f"left={os.path.join(args.data, 'left*.jpg')}", "--camera",
                   f"right={os.path.join(args.data, 'right*.jpg')}", "--out", take_dir,
                   "--overwrite"])
    if rc != 0:
        sys.exit(f"calibration_peers.py: import images failed: {out}")
    print("# " + out.strip().splitlines()[0])
    images = os.path.join(work, "images")
    if os.path.exists(images):
        shutil.rmtree(images)
    rc, out = run([args.holocap, "export", "images", take_dir, "--out", images, "--format", "png"])
    if rc != 0:
        sys.exit(f"calibration_peers.py: export images failed: {out}")
    take = RealTake(take_dir, args.board, images)
    default = solve_holocap_real(args, take, work, None)
    opencv5 = solve_holocap_real(args, take, work, "LENSMODEL_OPENCV5")
    why = "mrgingham finds square grids only (--gridn N: N x N inner corners)"
    warp = solve_holocap_real(args, take, work, None, ("--board-warp",))
    rows = [("holocap", "holocap", "OPENCV8", default),
            ("holocap", "holocap", "OPENCV5", opencv5),
            ("holocap", "holocap", "OPENCV8", warp),
            ("mrcal", "holocap", "OPENCV8",
             solve_mrcal_real(args, take, work, "LENSMODEL_OPENCV8", "holocap-8")),
            ("mrcal", "holocap", "OPENCV5",
             solve_mrcal_real(args, take, work, "LENSMODEL_OPENCV5", "holocap-5")),
            ("opencv", "opencv", "standard", solve_opencv(take, work, None)),
            ("opencv", "holocap", "standard",
             solve_opencv(take, work, os.path.join(images, "holocap.vnl")))]
    for solver, _, _, r in rows:
        if solver == "opencv" and "models" in r:
            r["note"] = "; ".join(filter(None, (r["note"], "every point kept (no outlier "
                                                "rejection)")))
    print(f"# board {take.width_n} x {take.height_n} inner corners, {1000 * take.spacing:g} mm "
          "squares (assumed: lengths scale with it)")
    print(f"# mrgingham left out: {why}; this board has {take.width_n} x {take.height_n}")
    if "sigma" in opencv5:
        print_real_table(rows, take.cameras, opencv5["sigma"])
    else:
        print_real_table(rows, take.cameras, dict(
            intrinsics={c: [float("nan")] * 4 for c in take.cameras}, baseline_m=float("nan"),
            rotation_deg=float("nan")))
    d = corner_distances(take, images)
    if d.size:
        print(f"# corners, holocap against OpenCV's findChessboardCorners + cornerSubPix on the "
              f"same images: {d.size} corners, mean {d.mean():.3f} px, p95 "
              f"{np.percentile(d, 95):.3f} px, max {d.max():.3f} px")


def main_check(args):
    work = args.work or os.path.join("/tmp", f"calibration-peers-check-{os.getpid()}")
    os.makedirs(work, exist_ok=True)
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        layout = os.path.join(work, "square.yaml")
        with open(layout, "w") as f:
            f.write("type: chessboard\nchessboard_width_n: 8\nchessboard_height_n: 8\n"
                    "spacing: 0.07\nmargin: 0.2\n")
        take_dir = os.path.join(work, "take")
        for command in (
                [args.holocap, "sim", "--rig", os.path.join(here, "calibration_peers_rig.yaml"),
                 "--board", "--board-layout", layout, "--frames", "12", "--seed", "3",
                 "--overwrite", "--out", take_dir],
                [args.holocap, "calibrate", take_dir, "--no-pictures", "--no-uncertainty",
                 "--lens-model", "LENSMODEL_OPENCV5", "--write-corners",
                 os.path.join(work, "corners.vnl")]):
            rc, out = run(command)
            if rc != 0:
                print(out)
                sys.exit(f"calibration_peers.py: {' '.join(command[:2])} failed")
        failures = check_corners(Take(take_dir), os.path.join(work, "corners.vnl"), work)
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    for f in failures:
        print("FAILED:", f)
    sys.exit(1 if failures else 0)


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("--holocap", required=True)
    r.add_argument("--take", required=True)
    r.add_argument("--work", required=True)
    r.add_argument("--lensmodel", default="LENSMODEL_OPENCV5")
    r.add_argument("--focal", type=float, default=500,
                   help="mrcal-calibrate-cameras' seed focal length (a nominal guess, px)")
    r.add_argument("--splined", default="")
    real = sub.add_parser("real")
    real.add_argument("--holocap", required=True)
    real.add_argument("--data", required=True)
    real.add_argument("--work", required=True)
    real.add_argument("--focal", type=float, default=500,
                      help="mrcal-calibrate-cameras' seed focal length (a nominal guess, px)")
    c = sub.add_parser("check-corners")
    c.add_argument("--holocap", required=True)
    c.add_argument("--work", default="")
    args = parser.parse_args()
    {"run": main_run, "real": main_real, "check-corners": main_check}[args.command](args)


if __name__ == "__main__":
    main()
