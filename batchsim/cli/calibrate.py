"""`batchsim calibrate`: fit a model to a real robot's bag over N randomized worlds.

    batchsim calibrate real.mcap --model arm --randomize ranges.yaml --worlds 256 --rounds 5 \
        [--controllers controllers.yaml] [--out fitted.yaml] [--json fit.json] [--plot fit.png]

Prints a line per round (its best error and the next ranges), the fitted values and the RMS
error per joint before (the model as it is) and after (as fitted); --out writes a randomize
block centred on the fit (batchsim.calibration). Without --controllers a shipped model's own
controllers run (the arm's: a joint_trajectory_controller). A bag the robot does not fit is
one line, exit 2.
"""

from __future__ import annotations

from collections.abc import Sequence

from batchsim.cli.analysis_args import calibrate_parser
from batchsim.cli.args import UsageError
from batchsim.cli.reports import write_reports


def calibrate(argv: Sequence[str]) -> int:
    args = calibrate_parser().parse_args(argv)
    if args.worlds < 4:
        raise UsageError(f"--worlds must be >= 4 (a round narrows to its best worlds), got {args.worlds}")
    if args.rounds < 1:
        raise UsageError(f"--rounds must be >= 1, got {args.rounds}")
    if not 0 < args.elite <= 1:
        raise UsageError(f"--elite must be in (0, 1], got {args.elite:g}")

    import batchsim
    from batchsim.calibration.bag import BagError, read_bag
    from batchsim.calibration.fit import FitOptions
    from batchsim.calibration.fit import calibrate as fit_bag
    from batchsim.calibration.parameters import parameters
    from batchsim.calibration.replay import controller_inputs
    from batchsim.calibration.report import as_json, plot, round_line, table, yaml_block
    from batchsim.controllers import default_controllers, load_controllers
    from batchsim.variation import VariationError, load

    controllers = args.controllers or default_controllers(str(args.model))
    if controllers is None:
        raise UsageError(f"{args.model}: no default controllers; give the real robot's with --controllers FILE")
    try:
        ranges = load(args.randomize)
        spec = batchsim.load(args.model)
        inputs = controller_inputs(load_controllers(controllers, spec, 1))
        joints = [j.name for j in spec.joints]
        bag = read_bag(args.file, joints, {t: i.kind for t, i in inputs.items()}, args.namespace, f"the robot {spec.name}")
        print(
            f"{args.file}: {len(bag.times)} joint states of {len(bag.joints)} joints over {bag.duration:.2f} s, "
            f"{len(bag.commands)} commands ({', '.join(sorted({c.topic for c in bag.commands}))})"
        )
        params = parameters(ranges, spec.mjmodel)

        def progress(r: int, outcome, search, seconds: float) -> None:
            print(round_line(r, args.rounds, outcome, search, seconds, params), flush=True)

        options = FitOptions(args.worlds, args.rounds, args.elite, args.seed, args.backend)
        fit = fit_bag(bag, args.model, ranges, controllers, options, progress)
    except (BagError, VariationError) as e:
        raise UsageError(str(e)) from None
    print("\n".join(table(fit)))
    about = {
        "bag": str(args.file),
        "model": str(args.model),
        "controllers": str(controllers),
        "randomize": str(args.randomize),
        "worlds": args.worlds,
        "rounds": args.rounds,
        "seed": args.seed,
        "backend": args.backend,
    }
    if args.out is not None:
        header = (
            f"batchsim calibrate {args.file} --model {args.model} --randomize {args.randomize} "
            f"--worlds {args.worlds} --rounds {args.rounds} --seed {args.seed}\n"
            f"RMS error {float(fit.before.overall[0]):.3g} before, {float(fit.after.overall[0]):.3g} after"
        )
        args.out.write_text(yaml_block(fit, header))
        print(f"wrote {args.out}")
    title = f"calibration of {args.model} against {args.file}"
    write_reports(args.json, lambda: as_json(fit, about), args.plot, lambda path: plot(fit, path, title))
    return 0
