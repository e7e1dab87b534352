"""Direct and indirect parts of a run's PBR against the GT `direct` and indirect (RGBA) layers of
indirect.exr (needs `pip install openexr`); ratio picture of one view.  usage: split_map.py RUN VIEW

Throw-away diagnostics (numpy, PIL) for the shared spheres scene; not part of the build or tests."""
import numpy as np, sys, OpenEXR
from PIL import Image
data='/work/shared/data/spheres'; run=sys.argv[1]; views=range(16)
def lin(a): a=a/255.0; return np.where(a<=0.04045,a/12.92,((a+0.055)/1.055)**2.4)
ld=lambda p: np.asarray(Image.open(p).convert('RGBA')).astype(float)
def col(r,m):
    x=np.clip(np.log2(r),-1,1); im=np.zeros(r.shape+(3,))
    im[...,0]=np.where(x>0,x,0); im[...,2]=np.where(x<0,-x,0); im[~m]=0.5
    return (im*255).astype(np.uint8)
tot=np.zeros(4)
for v in views:
    f=OpenEXR.File(f'{data}/test_{v:03d}/indirect.exr').channels()
    gd=np.asarray(f['direct'].pixels,dtype=float)[...,:3]; gi=np.asarray(f['RGBA'].pixels,dtype=float)[...,:3]
    ga=ld(f'{data}/test_{v:03d}/albedo.png'); m=ga[...,3]>250
    pb=lin(ld(f'{run}/eval/test_{v:03d}_pbr.png')[...,:3]); oi=lin(ld(f'{run}/eval/test_{v:03d}_indirect.png')[...,:3])
    od=np.maximum(pb-oi,0)
    tot+=[gd[m].mean(),od[m].mean(),gi[m].mean(),oi[m].mean()]
    if v==int(sys.argv[2]):
        r1=(gd.mean(2)+1e-3)/(od.mean(2)+1e-3); r2=(gi.mean(2)+1e-3)/(oi.mean(2)+1e-3)
        im=np.concatenate([col(r1,m),col(r2,m)],1)
        Image.fromarray(im).resize((800,400),Image.NEAREST).save(f'/work/diag/split_{v}.png')
print('mean over masks: GT direct %.4f ours %.4f | GT indirect %.4f ours %.4f'%tuple(tot/16))
