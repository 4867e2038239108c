import torch, kornia
from naka_gs_plugin.enhance.exposure import lift_gamma, apply_gamma
exec(open(__file__.rsplit('/', 1)[0] + '/chroma.py').read().split('tot={}')[0])
def cfl(net, low, k=9, conf=None, jb=None, Yw=False):
    lowc=low.permute(2,0,1)[None]; E=lin(net.permute(2,0,1)[None])
    if jb: L=lin(kornia.filters.joint_bilateral_blur(lowc, net.permute(2,0,1)[None], (k,k), jb, (k/3,k/3)))
    else: L=lin(kornia.filters.gaussian_blur2d(lowc,(k,k),(k/3,k/3)))
    Ec=E/(E.mean(1,keepdim=True)+1e-4)
    c=L/(L.mean(1,keepdim=True)+1e-4)
    if conf:
        w=L.mean(1,keepdim=True); w=w/(w+conf); c=w*c+(1-w)*Ec
    Y=E.mean(1,keepdim=True)
    return srgb((Y*c).clamp(0,1))[0].permute(1,2,0)
tot={}
for s in ["bike","chair","shrub","sofa"]:
    d=torch.load(f"/tmp/exp/{s}.pt")
    tr=[v for v in d.values() if v["split"]=="train"]; te=[v for v in d.values() if v["split"]=="test"]
    g=lift_gamma([v["net"].float() for v in tr])
    g2=lift_gamma([cfl(v["net"].float(),v["low"].float()) for v in tr])
    print(s,"g",g,"g after chroma",g2)
    V={"mg+low k9":lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float()),
       "low k9+mg":lambda v:apply_gamma([cfl(v["net"].float(),v["low"].float())],g2)[0],
       "mg+k13":lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float(),13),
       "mg+conf1e-4":lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float(),conf=1e-4),
       "mg+conf5e-4":lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float(),conf=5e-4),
       "mg+jb0.1":lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float(),jb=0.1),
       }
    for name,fn in V.items():
        ims=[fn(v) for v in te]
        P=sum(psnr(i,v["truth"].float()) for i,v in zip(ims,te))/len(te); Q=sum(ssim(i,v["truth"].float()) for i,v in zip(ims,te))/len(te)
        tot.setdefault(name,[]).append((P,Q))
        print(s,"%-16s %.2f %.3f sat %.3f"%(name,P,Q,sat(torch.cat([i.reshape(-1,3) for i in ims]))))
for k,v in tot.items(): print("MEAN %-16s %.2f %.3f"%(k,sum(a for a,_ in v)/4,sum(b for _,b in v)/4))
