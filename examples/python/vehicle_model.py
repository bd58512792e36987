"""The vehicle model from Python: generate experiment A, learn the model from the
fresh start `sefi train` uses with a progress callback, then filter and smooth
the test objects and compare the estimates with the truth.

    python examples/python/vehicle_model.py            # the small sizes (seconds)
    python examples/python/vehicle_model.py --paper    # experiment A at the paper's sizes

Prints the test MLL before and after, the learned policy sds against the truth,
and the smoothed and filtered position errors; plots the learning curve to
vehicle_model.png when matplotlib is installed.
"""

import argparse

import numpy as np

import pfsefi


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--paper", action="store_true", help="experiment A at the paper's sizes (slow)")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    train, test, truth = pfsefi.generate_experiment("A", seed=args.seed, quick=not args.paper)
    print(train, test, sep="\n")
    start = pfsefi.VehicleModel.initial(train, init_sd=(2.0, 0.2), seed=args.seed)

    losses = []

    def progress(step, loss):
        losses.append(loss)
        if step % 10 == 0:
            print(f"step {step:4d}  training loss {loss:.3f} nats/point")

    result = start.train(test, epochs=args.epochs, lr=0.02, particles=256, eval_particles=1024, lag=8,
                         seed=args.seed, eval_every=max(1, train.num_scenes), callback=progress)
    evals = result["evaluations"]
    print(f"test MLL {evals[0][1]['test_mll']:.3f} -> {evals[-1][1]['test_mll']:.3f} nats/point "
          f"({result['steps']} steps, {result['seconds']:.1f} s)")
    learned = np.exp(result["model"].parameters["policy.log_sd"])
    print("policy sds (accel, pinch): learned", learned.round(3), "true", np.exp(truth["policy.log_sd"]).round(3))

    model = result["model"].on(test)
    tracks = model.filter(particles=1024, lag=8, seed=1)
    for which in ["filtered", "smoothed"]:
        err = [np.hypot(*(tracks[which][i, :, :2] - test.truth(i)[:, :2]).T) for i in range(test.num_objects)]
        print(f"{which:>8} position error {np.mean(np.concatenate(err)):.3f} m")

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(np.arange(1, len(losses) + 1), losses, lw=0.8, label="training loss")
    ax.plot([s for s, _ in evals], [-e["test_mll"] for _, e in evals], "o-", label="test loss")
    ax.set_xlabel("step")
    ax.set_ylabel("nats per point")
    ax.legend()
    fig.tight_layout()
    fig.savefig("vehicle_model.png", dpi=120)
    print("wrote vehicle_model.png")


if __name__ == "__main__":
    main()
