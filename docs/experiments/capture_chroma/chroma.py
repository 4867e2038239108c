import torch, kornia
def psnr(a,b): return float(-10*torch.log10(((a-b)**2).mean()))
def ssim(a,b): return float(kornia.metrics.ssim(a.permute(2,0,1)[None],b.permute(2,0,1)[None],11).mean())
def sat(x):
    mx=x.max(-1).values; mn=x.min(-1).values
    return float(((mx-mn)/(mx+1e-3)).mean())
lin=kornia.color.rgb_to_linear_rgb; srgb=kornia.color.linear_rgb_to_rgb
def chroma_from_low(net, low, k=9, alpha=1.0):
    L=lin(kornia.filters.gaussian_blur2d(low.permute(2,0,1)[None],(k,k),(k/3,k/3)))
    c=L/(L.mean(1,keepdim=True)+1e-4)
    E=lin(net.permute(2,0,1)[None])
    Ec=E/(E.mean(1,keepdim=True)+1e-4)
    cc=Ec*(c/Ec.clamp(min=1e-3))**alpha if False else (1-alpha)*Ec+alpha*c
    out=srgb((E.mean(1,keepdim=True)*cc).clamp(0,1))
    return out[0].permute(1,2,0)
def chroma_scale(net, s):
    E=lin(net.permute(2,0,1)[None]); Y=E.mean(1,keepdim=True)
    return srgb((Y+(E-Y)*s).clamp(0,1))[0].permute(1,2,0)
tot={}
for s in ["bike","chair","shrub","sofa"]:
    d=torch.load(f"/tmp/exp/{s}.pt")
    te=[v for v in d.values() if v["split"]=="test"]
    V={"net":lambda v:v["net"].float()}
    for k in (5,9,17):
        for a in (0.5,1.0):
            V[f"low k{k} a{a}"]=(lambda k,a:lambda v:chroma_from_low(v["net"].float(),v["low"].float(),k,a))(k,a)
    for sc in (1.3,1.6,2.0):
        V[f"scale{sc}"]=(lambda sc:lambda v:chroma_scale(v["net"].float(),sc))(sc)
    V["truthchroma"]=lambda v:chroma_from_low(v["net"].float(),v["truth"].float(),1,1.0)
    for name,fn in V.items():
        ims=[fn(v) for v in te]
        P=sum(psnr(i,v["truth"].float()) for i,v in zip(ims,te))/len(te); Q=sum(ssim(i,v["truth"].float()) for i,v in zip(ims,te))/len(te)
        tot.setdefault(name,[]).append((P,Q))
        print(s,"%-16s %.2f %.3f sat %.3f"%(name,P,Q,sat(torch.cat([i.reshape(-1,3) for i in ims]))))
for k,v in tot.items(): print("MEAN %-16s %.2f %.3f"%(k,sum(a for a,_ in v)/4,sum(b for _,b in v)/4))
