"""The heavy-tail families of `sefi generate` and the Gaussian, as the scripts of this
folder use them: draws from the module-level `random` stream (so a script that seeds
`random` gets the same draws as before these were shared), log-densities, and how far
a sample's truth is above the Gaussian the sample fits. Standard library only."""
import math
import random


def t_draw(nu):
    """A standard Student-t draw with `nu` degrees of freedom."""
    z = random.gauss(0, 1)
    c = random.gammavariate(nu / 2, 2.0)
    return z / math.sqrt(c / nu)


def t_logpdf(x, nu):
    """The standard Student-t log-density."""
    return math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) - 0.5 * math.log(nu * math.pi) - (nu + 1) / 2 * math.log1p(x * x / nu)


def n_logpdf(x, s):
    """The zero-mean Gaussian log-density of sd `s`."""
    return -0.5 * math.log(2 * math.pi * s * s) - x * x / (2 * s * s)


def mix_logpdf(x, p, k):
    """The zero-mean two-normal mixture: sd 1 with probability 1 - p, sd k with p."""
    l1 = math.log(1 - p) + n_logpdf(x, 1.0)
    l2 = math.log(p) + n_logpdf(x, k)
    m = max(l1, l2)
    return m + math.log(math.exp(l1 - m) + math.exp(l2 - m))


def gap_to_sample_gaussian(xs, logp):
    """The truth's log-likelihood per innovation of `xs` above the zero-mean Gaussian
    they fit (their own variance)."""
    s = math.sqrt(sum(x * x for x in xs) / len(xs))
    return sum(logp(x) - n_logpdf(x, s) for x in xs) / len(xs)
