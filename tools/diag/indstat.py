"""Mean blend-weight fractions (deep / surface / outside) over the GT mask of the pictures that
`radiogs render --run OUT --mode albedo` made of an indicator.py copy.  usage: indstat.py RENDER_DIR

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys
from PIL import Image
d=sys.argv[1]; data='/work/shared/data/spheres'
def lin(a): a=a/255.0; return np.where(a<=0.04045,a/12.92,((a+0.055)/1.055)**2.4)
acc=[]
for v in range(16):
    gt=np.asarray(Image.open(f'{data}/test_{v:03d}/albedo.png').convert('RGBA')).astype(float)
    pr=np.asarray(Image.open(f'{d}/test_{v:03d}.png').convert('RGBA')).astype(float)
    m=gt[...,3]>127
    p=(lin(pr[...,:3])-0.03)/0.77
    acc.append(p[m])
A=np.concatenate(acc)
print('weight fraction deep-in / surface band / outside (mean over GT mask):',np.round(A.mean(0),3))
print('pixels with deep-in fraction >0.1: %.3f  >0.3: %.3f'%((A[:,0]>0.1).mean(),(A[:,0]>0.3).mean()))
