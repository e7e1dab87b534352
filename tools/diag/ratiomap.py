"""Picture + correlation: log(GT radiance / oracle PBR) vs log(learned albedo / GT albedo) per pixel.
usage: ratiomap.py VIEW RUN   (expects the oracle run at /work/runs/sph_or0; edit for yours)

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys
from PIL import Image
data='/work/shared/data/spheres'; v=int(sys.argv[1])
def lin(a): a=a/255.0; return np.where(a<=0.04045,a/12.92,((a+0.055)/1.055)**2.4)
ld=lambda p: np.asarray(Image.open(p).convert('RGBA')).astype(float)
gt=ld(f'{data}/test_{v:03d}/rgba.png'); ga=ld(f'{data}/test_{v:03d}/albedo.png')
orp=ld(f'/work/runs/sph_or0/eval/test_{v:03d}_pbr.png'); la=ld(f'/work/runs/{sys.argv[2]}/eval/test_{v:03d}_albedo.png')
m=ga[...,3]>127
r1=(lin(gt[...,:3]).mean(2)+1e-3)/(lin(orp[...,:3]).mean(2)+1e-3)   # GT radiance / ours with true materials
r2=(lin(la[...,:3]).mean(2)+1e-3)/(lin(ga[...,:3]).mean(2)+1e-3)    # learned albedo / true albedo
def col(r):
    x=np.clip(np.log2(r)/1.0,-1,1); im=np.zeros(r.shape+(3,))
    im[...,0]=np.where(x>0,x,0); im[...,2]=np.where(x<0,-x,0); im[...,1]=0; im[~m]=0.5
    return (im*255).astype(np.uint8)
W=np.concatenate([col(r1),col(r2)],1)
Image.fromarray(W).resize((800,400),Image.NEAREST).save(f'/work/diag/ratio_{v}.png')
mm=m&(lin(ga[...,:3]).mean(2)>0.3)
print('corr(log r1, log r2) over masked bright-albedo px:',np.corrcoef(np.log(r1[mm]),np.log(r2[mm]))[0,1])
print('corr all masked:',np.corrcoef(np.log(r1[m]),np.log(r2[m]))[0,1])
