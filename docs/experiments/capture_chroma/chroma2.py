import torch, kornia
from naka_gs_plugin.enhance.exposure import lift_gamma, apply_gamma
exec(open(__file__.rsplit('/', 1)[0] + '/chroma.py').read().split('tot={}')[0])
def cfl(net, low, k=9, q=None, scene_black=None):
    L=lin(kornia.filters.gaussian_blur2d(low.permute(2,0,1)[None],(k,k),(k/3,k/3)))
    if scene_black is not None: L=(L-scene_black.view(1,3,1,1)).clamp(min=0)
    elif q is not None:
        b=torch.quantile(L.reshape(3,-1)[:, ::13],q,dim=1).view(1,3,1,1); L=(L-b).clamp(min=0)
    c=L/(L.mean(1,keepdim=True)+1e-4)
    E=lin(net.permute(2,0,1)[None]); Y=E.mean(1,keepdim=True)
    return srgb((Y*c).clamp(0,1))[0].permute(1,2,0)
tot={}
for s in ["bike","chair","shrub","sofa"]:
    d=torch.load(f"/tmp/exp/{s}.pt")
    tr=[v for v in d.values() if v["split"]=="train"]; te=[v for v in d.values() if v["split"]=="test"]
    g=lift_gamma([v["net"].float() for v in tr])
    allL=torch.cat([lin(v["low"].float().permute(2,0,1)).reshape(3,-1).T[::17] for v in tr])
    sb={q:torch.quantile(allL,q,dim=0) for q in (0.001,0.01)}
    print(s,"scene black",{q:[round(float(x)*255,2) for x in b] for q,b in sb.items()})
    V={"low k9":lambda v:cfl(v["net"].float(),v["low"].float())}
    for q in (0.001,0.01,0.05): V[f"img q{q}"]=(lambda q:lambda v:cfl(v["net"].float(),v["low"].float(),q=q))(q)
    for q in (0.001,0.01): V[f"scene q{q}"]=(lambda q:lambda v:cfl(v["net"].float(),v["low"].float(),scene_black=sb[q]))(q)
    V["mg+low k9"]=lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float())
    V["mg+scene q0.01"]=lambda v:cfl(apply_gamma([v["net"].float()],g)[0],v["low"].float(),scene_black=sb[0.01])
    for name,fn in V.items():
        ims=[fn(v) for v in te]
        P=sum(psnr(i,v["truth"].float()) for i,v in zip(ims,te))/len(te); Q=sum(ssim(i,v["truth"].float()) for i,v in zip(ims,te))/len(te)
        tot.setdefault(name,[]).append((P,Q))
        print(s,"%-16s %.2f %.3f sat %.3f"%(name,P,Q,sat(torch.cat([i.reshape(-1,3) for i in ims]))))
for k,v in tot.items(): print("MEAN %-16s %.2f %.3f"%(k,sum(a for a,_ in v)/4,sum(b for _,b in v)/4))
