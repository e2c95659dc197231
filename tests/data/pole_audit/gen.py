# ruff: noqa  (kept as the user-auditor wrote it, session 40; only this line added)
import numpy as np, sys, time
from truth import *
inst_name = sys.argv[1]; n = int(sys.argv[2])
inst = {'portable': PORTABLE, 'wide': WIDE}[inst_name]
m = cie_mask()
T, B = np.meshgrid(TAN, BETA, indexing='ij')
rt = np.where(m, r_true(T, B), np.nan)
ka = np.full((29,20), np.nan); ka2 = np.full((29,20), np.nan)
p1 = qmc.Sobol(6, scramble=True, seed=11).random(2**n)
p2 = qmc.Sobol(6, scramble=True, seed=12).random(2**n)
t0=time.time()
for i in range(29):
    for j in range(20):
        if m[i,j]:
            ka[i,j] = ka_cell(inst, TAN[i], BETA[j], p1)
            ka2[i,j] = ka_cell(inst, TAN[i], BETA[j], p2)
print('time', time.time()-t0)
k = 0.5*(ka+ka2); se = np.abs(ka-ka2)/2
print('k_A range', np.nanmin(k), np.nanmax(k), 'max rel diff/2', np.nanmax(se/k))
rng = np.random.default_rng(20261207)
noise = 1 + 0.01*rng.standard_normal((29,20))
rm = rt*k*noise
np.savez(f'{inst_name}_truth.npz', r_true=rt, ka=k, ka_se=se, noise=noise, r_meas=rm)
write_table(f'measured_{inst_name}.csv', rm*1e4, f'audit surface: GGX(m=0.25)+Lambert+beta bump truth x own k_A ({inst_name}) x 1% noise')
write_table(f'truth.csv', rt*1e4, 'audit surface truth: GGX(m=0.25)+Lambert+beta bump')
